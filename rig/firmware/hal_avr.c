/*
 * The hardware interface on an ATmega328P at 16 MHz (Arduino Uno / Nano).
 * Wiring: README.md. Resources used:
 *
 *   USART0   115200 8N1, receive interrupt into a ring buffer
 *   Timer1   free-running at F_CPU / 8 = 2 MHz: the step clock
 *   SPI      master, mode 0, MSB first, F_CPU / 16 = 1 MHz: the 74HC595 chain
 *
 * Pins (Arduino name / port bit):
 *   D2 PD2  STEP   (driver)      D8  PB0  end stop (to GND, internal pull-up)
 *   D3 PD3  DIR    (driver)      D9  PB1  74HC595 /OE (10k pull-up to 5 V)
 *   D4 PD4  /EN    (driver)      D10 PB2  74HC595 RCLK (latch)
 *                                D11 PB3  74HC595 SER  (SPI MOSI)
 *                                D13 PB5  74HC595 SRCLK (SPI SCK)
 */
#ifndef F_CPU
#define F_CPU 16000000UL
#endif

#include <avr/interrupt.h>
#include <avr/io.h>
#include <avr/sleep.h>
#include <util/delay.h>

#include "hal.h"

#define STEP_BIT PD2
#define DIR_BIT PD3
#define EN_BIT PD4
#define ENDSTOP_BIT PB0
#define OE_BIT PB1
#define RCLK_BIT PB2
#define SER_BIT PB3
#define SRCLK_BIT PB5

/*
 * 115200 baud with U2X: UBRR = F_CPU / (8 * 115200) - 1 = 16.4 -> 16, i.e.
 * 117647 baud, +2.1 %. Within the receiver's tolerance at 8N1 (about
 * +-3.9 % in double speed mode for both ends together). On the Uno the
 * USB-serial chip (ATmega16U2, also 16 MHz) uses the same divisor, so the two
 * agree exactly; FTDI/CH340 bridges (Nano) make 115200 exactly, 2.1 % off.
 * Without U2X the error would be -3.5 %.
 */
#define UART_UBRR 16

/* Receive ring buffer, filled by the interrupt. Power of two, < 256. */
#define RX_SIZE 128u
#define RX_MASK (RX_SIZE - 1u)

static volatile uint8_t rx_buf[RX_SIZE];
static volatile uint8_t rx_head;   /* written by the ISR only */
static volatile uint8_t rx_tail;   /* written by the main loop only */

static uint16_t step_deadline;     /* Timer1 ticks (0.5 us) of the last step */

ISR(USART_RX_vect)
{
    uint8_t status = UCSR0A;
    uint8_t byte = UDR0;              /* reading UDR0 clears the interrupt */
    uint8_t next = (uint8_t)((rx_head + 1u) & RX_MASK);

    if (status & _BV(FE0))            /* framing error: noise or wrong baud, drop */
        return;
    if (next != rx_tail) {            /* full: drop (only if the host breaks request/reply) */
        rx_buf[rx_head] = byte;
        rx_head = next;
    }
}

static void uart_init(void)
{
    UBRR0 = UART_UBRR;
    UCSR0A = _BV(U2X0);
    UCSR0C = _BV(UCSZ01) | _BV(UCSZ00);                 /* 8 data bits, no parity, 1 stop bit */
    UCSR0B = _BV(RXEN0) | _BV(TXEN0) | _BV(RXCIE0);
}

static void motor_pins_init(void)
{
    PORTD |= _BV(EN_BIT);                                /* /EN high: driver off */
    PORTD &= (uint8_t)~(_BV(STEP_BIT) | _BV(DIR_BIT));
    DDRD |= _BV(STEP_BIT) | _BV(DIR_BIT) | _BV(EN_BIT);
    DDRB &= (uint8_t)~_BV(ENDSTOP_BIT);
    PORTB |= _BV(ENDSTOP_BIT);                           /* internal pull-up: open switch reads high */
}

static void led_chain_init(void)
{
    static const uint8_t dark[HAL_LED_FRAME_BYTES];

    PORTB |= _BV(OE_BIT);                                /* outputs off while the registers hold noise */
    PORTB &= (uint8_t)~(_BV(RCLK_BIT) | _BV(SER_BIT) | _BV(SRCLK_BIT));
    DDRB |= _BV(OE_BIT) | _BV(RCLK_BIT) | _BV(SER_BIT) | _BV(SRCLK_BIT);
    /* RCLK is SS: as an output it keeps the SPI in master mode. */
    SPCR = _BV(SPE) | _BV(MSTR) | _BV(SPR0);             /* mode 0, MSB first, F_CPU / 16 */
    hal_leds_latch(dark);
    PORTB &= (uint8_t)~_BV(OE_BIT);                      /* registers defined: enable the outputs */
}

void hal_init(void)
{
    cli();
    motor_pins_init();
    led_chain_init();
    TCCR1A = 0;
    TCCR1B = _BV(CS11);                                  /* Timer1 normal mode, F_CPU / 8 */
    uart_init();
    set_sleep_mode(SLEEP_MODE_IDLE);                     /* idle keeps the USART running */
    sei();
}

int hal_uart_read(void)
{
    uint8_t byte;

    if (rx_tail == rx_head)
        return -1;
    byte = rx_buf[rx_tail];
    rx_tail = (uint8_t)((rx_tail + 1u) & RX_MASK);
    return byte;
}

void hal_uart_write(uint8_t byte)
{
    loop_until_bit_is_set(UCSR0A, UDRE0);
    UDR0 = byte;
}

void hal_idle(void)
{
    /*
     * Sleep unless a byte is waiting. Interrupts are off while checking; the
     * instruction after sei() (sleep) always runs before a pending interrupt,
     * so a byte that arrives between the check and the sleep wakes the CPU
     * instead of being noticed only with the next one.
     */
    cli();
    if (rx_tail == rx_head) {
        sleep_enable();
        sei();
        sleep_cpu();
        sleep_disable();
    }
    sei();
}

void hal_motor_enable(bool on)
{
    if (on)
        PORTD &= (uint8_t)~_BV(EN_BIT);
    else
        PORTD |= _BV(EN_BIT);
}

void hal_motor_dir(bool away_from_home)
{
    if (away_from_home)
        PORTD |= _BV(DIR_BIT);
    else
        PORTD &= (uint8_t)~_BV(DIR_BIT);
    _delay_us(1);   /* DIR setup before the STEP edge: A4988 200 ns, TMC2209 20 ns */
}

void hal_step(void)
{
    PORTD |= _BV(STEP_BIT);
    _delay_us(2);   /* STEP high >= 1 us (A4988); the low time is the step period */
    PORTD &= (uint8_t)~_BV(STEP_BIT);
}

bool hal_endstop_active(void)
{
    return bit_is_clear(PINB, ENDSTOP_BIT);   /* closed switch pulls the pin to GND */
}

void hal_leds_latch(const uint8_t frame[HAL_LED_FRAME_BYTES])
{
    int8_t i;

    /*
     * The first byte shifted in ends in the last register of the chain, so
     * send the far register (highest LEDs) first. MSB first: bit k lands on
     * output Qk (QA = bit 0). 40 bits at 1 MHz: 40 us.
     */
    for (i = HAL_LED_FRAME_BYTES - 1; i >= 0; i--) {
        SPDR = frame[i];
        loop_until_bit_is_set(SPSR, SPIF);
    }
    PORTB |= _BV(RCLK_BIT);   /* rising edge copies the shift registers to the outputs */
    _delay_us(1);
    PORTB &= (uint8_t)~_BV(RCLK_BIT);
}

void hal_step_timer_start(void)
{
    step_deadline = TCNT1;
}

void hal_step_wait(uint16_t interval_us)
{
    /*
     * Ticks are 0.5 us; the longest interval (5000 us at 200 steps/s) is
     * 10000 ticks, inside the 16-bit counter's 32.7 ms (clamped to 16 ms),
     * and the unsigned differences below stay correct across its wrap-around.
     */
    uint16_t ticks;

    if (interval_us > 16000u)
        interval_us = 16000u;
    ticks = (uint16_t)(interval_us * 2u);

    if ((uint16_t)(TCNT1 - step_deadline) >= ticks) {
        step_deadline = TCNT1;   /* late (never at these rates): restart the schedule */
        return;
    }
    while ((uint16_t)(TCNT1 - step_deadline) < ticks) {
    }
    step_deadline += ticks;
}

void hal_delay_ms(uint16_t ms)
{
    while (ms-- > 0)
        _delay_ms(1);
}
