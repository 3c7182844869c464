/*
 * Hardware interface of the rig controller. The protocol (protocol.c) and the
 * motion control (motion.c) are portable C and reach the hardware only
 * through these functions:
 *
 *   hal_avr.c   ATmega328P at 16 MHz (Arduino Uno/Nano): USART0, STEP/DIR/EN
 *               of an A4988/TMC2209 driver, end stop, 74HC595 chain over SPI.
 *   hal_host.c  Linux: the UART is stdin/stdout (raw bytes), the carriage and
 *               its end stop are simulated.
 *
 * Nothing here allocates memory; all functions are called from the main loop
 * only (never from an interrupt).
 */
#ifndef FACETSYNTH_RIG_HAL_H
#define FACETSYNTH_RIG_HAL_H

#include <stdbool.h>
#include <stdint.h>

#include "config.h"

#define HAL_LED_FRAME_BYTES ((RIG_N_LEDS + 7) / 8)   /* one 74HC595 per byte */

/* Set up pins and peripherals. Afterwards: LEDs off, motor driver disabled. */
void hal_init(void);

/* Next received byte (0..255), or -1 if none is waiting. Never blocks. */
int hal_uart_read(void);

/* Send one byte; blocks until the transmitter has taken it. */
void hal_uart_write(uint8_t byte);

/* Sleep until something may have happened (a byte received). May return early. */
void hal_idle(void);

/* Motor driver outputs on (holding torque) or off (carriage free). */
void hal_motor_enable(bool on);

/* Direction of the following steps: true = away from the end stop (steps increase). */
void hal_motor_dir(bool away_from_home);

/* One step pulse on STEP. */
void hal_step(void);

/* Whether the home end stop is closed. */
bool hal_endstop_active(void);

/*
 * Show an LED frame: bit k of frame[i] drives LED 8 i + k (1 = lit). Latched
 * at once, so all outputs change together.
 */
void hal_leds_latch(const uint8_t frame[HAL_LED_FRAME_BYTES]);

/*
 * Step timing. hal_step_timer_start() marks "now" as the time of the last
 * step; each hal_step_wait(us) then returns us microseconds after the previous
 * deadline (not after the call), so the time spent between steps (polling
 * the UART, computing the ramp) does not stretch the step period. If the
 * deadline has already passed it returns at once and restarts from now.
 */
void hal_step_timer_start(void);
void hal_step_wait(uint16_t interval_us);

/* Busy-wait about ms milliseconds. */
void hal_delay_ms(uint16_t ms);

#endif
