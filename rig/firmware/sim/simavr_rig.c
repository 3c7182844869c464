/*
 * Runs the AVR image (build/facetsynth-rig.elf) in simavr on a simulated
 * ATmega328P at 16 MHz, wired like the real rig:
 *
 *   USART0        stdin/stdout (raw bytes), as for rig-host: give the process
 *                 one end of a pseudo-terminal
 *   PD2/PD3/PD4   STEP/DIR//EN of the driver: a simulated carriage, moved by
 *                 STEP rising edges while /EN is low
 *   PB0           end stop: driven low (closed) while the carriage is at
 *                 position <= 0
 *   SPI + PB2     the 74HC595 chain: the last 5 bytes shifted are latched on
 *                 the rising edge of RCLK
 *
 * Unlike rig-host this runs the real image, the real UART timing and the real
 * step timing (the firmware's ramp at up to 4000 steps/s of simulated time).
 *
 * Usage: rig-simavr <firmware.elf>. Environment: FIRMWARE_START_STEPS and
 * FIRMWARE_TRACE as for rig-host (hal_host.c); FIRMWARE_TRACE logs the
 * latched LED frames and the /EN edges with the carriage position to stderr.
 * End of input ends the process.
 */
#define _GNU_SOURCE   /* ppoll */

#include <errno.h>
#include <poll.h>
#include <stdarg.h>
#include <stdbool.h>
#include <stdio.h>
#include <stdlib.h>
#include <string.h>
#include <time.h>
#include <unistd.h>

#include <avr_ioport.h>
#include <avr_spi.h>
#include <avr_uart.h>
#include <sim_avr.h>
#include <sim_elf.h>
#include <sim_irq.h>
#include <sim_time.h>

#include "../config.h"

#define LED_BYTES ((RIG_N_LEDS + 7) / 8)
#define RUN_BATCH 2000   /* instructions between two looks at stdin */

static avr_t *avr;
static avr_irq_t *uart_in;
static avr_irq_t *endstop_pin;

static uint8_t input[256];       /* bytes read from stdin, not yet in the UART */
static size_t input_len, input_pos;
static bool uart_xoff;

static long carriage = 2000;     /* steps from the end stop */
static bool step_level, dir_away, motor_on;
static uint8_t chain[LED_BYTES]; /* chain[0] = first register (LEDs 0..7) */
static bool rclk_level;
static bool trace;

static void logger(avr_t *a, const int level, const char *format, va_list ap)
{
    (void)a;
    if (level <= LOG_WARNING)
        vfprintf(stderr, format, ap);   /* never stdout: that is the UART */
}

/*
 * Bytes go to the UART only after the first simulated millisecond: simavr,
 * like the chip, drops what arrives before the firmware has enabled the
 * receiver (hal_init() takes microseconds). The rig behaves as if it had been
 * powered up before the host opened the port.
 */
#define STARTUP_CYCLES 16000u

static void feed_uart(void)
{
    if (avr->cycle < STARTUP_CYCLES)
        return;
    while (!uart_xoff && input_pos < input_len)
        avr_raise_irq(uart_in, input[input_pos++]);
}

/* Read what stdin has, waiting at most timeout_us for it (0: do not wait). */
static void read_stdin(uint32_t timeout_us)
{
    struct pollfd pfd = { STDIN_FILENO, POLLIN, 0 };
    struct timespec timeout = { timeout_us / 1000000u, (long)(timeout_us % 1000000u) * 1000L };
    ssize_t n;

    if (input_pos < input_len || ppoll(&pfd, 1, &timeout, NULL) <= 0)
        return;
    n = read(STDIN_FILENO, input, sizeof input);
    if (n == 0 || (n < 0 && errno != EINTR && errno != EAGAIN))
        exit(0);   /* the host closed the line: power off */
    if (n > 0) {
        input_len = (size_t)n;
        input_pos = 0;
    }
}

static void on_uart_output(avr_irq_t *irq, uint32_t value, void *param)
{
    uint8_t byte = (uint8_t)value;

    (void)irq;
    (void)param;
    if (write(STDOUT_FILENO, &byte, 1) != 1)
        exit(0);
}

static void on_xon(avr_irq_t *irq, uint32_t value, void *param)
{
    (void)irq;
    (void)value;
    (void)param;
    uart_xoff = false;
    feed_uart();
}

static void on_xoff(avr_irq_t *irq, uint32_t value, void *param)
{
    (void)irq;
    (void)value;
    (void)param;
    uart_xoff = true;
}

static void update_endstop(void)
{
    avr_raise_irq(endstop_pin, carriage <= 0 ? 0 : 1);
}

static void on_step(avr_irq_t *irq, uint32_t value, void *param)
{
    (void)irq;
    (void)param;
    if (value && !step_level && motor_on) {
        carriage += dir_away ? 1 : -1;
        update_endstop();
    }
    step_level = value != 0;
}

static void on_dir(avr_irq_t *irq, uint32_t value, void *param)
{
    (void)irq;
    (void)param;
    dir_away = value != 0;
}

static void on_enable(avr_irq_t *irq, uint32_t value, void *param)
{
    bool on = value == 0;   /* /EN: active low */

    (void)irq;
    (void)param;
    if (on != motor_on && trace)
        fprintf(stderr, "motor %s carriage=%ld\n", on ? "on" : "off", carriage);
    motor_on = on;
}

static void on_spi(avr_irq_t *irq, uint32_t value, void *param)
{
    (void)irq;
    (void)param;
    memmove(chain + 1, chain, LED_BYTES - 1);   /* every register passes its byte on */
    chain[0] = (uint8_t)value;
}

static void on_rclk(avr_irq_t *irq, uint32_t value, void *param)
{
    int i;

    (void)irq;
    (void)param;
    if (value && !rclk_level && trace) {
        fprintf(stderr, "leds");
        for (i = 0; i < LED_BYTES; i++)
            fprintf(stderr, " %02x", chain[i]);
        fprintf(stderr, "\n");
    }
    rclk_level = value != 0;
}

/*
 * The CPU sleeps (idle, waiting for a byte) for `cycles`: spend that time
 * waiting for stdin instead of spinning, so that an idle controller costs no
 * host CPU. simavr's accumulator hands out the short sleeps in chunks long
 * enough to be timed; simulated time then runs at the real-time rate.
 */
static void on_sleep(avr_t *a, avr_cycle_count_t cycles)
{
    read_stdin(avr_pending_sleep_usec(a, cycles));
    feed_uart();
}

static void notify(char port, int pin, avr_irq_notify_t fn)
{
    avr_irq_register_notify(avr_io_getirq(avr, AVR_IOCTL_IOPORT_GETIRQ(port), pin), fn, NULL);
}

static void wire_up(void)
{
    uint32_t flags = 0;

    avr_ioctl(avr, AVR_IOCTL_UART_GET_FLAGS('0'), &flags);
    flags &= ~(uint32_t)(AVR_UART_FLAG_STDIO | AVR_UART_FLAG_POLL_SLEEP);
    avr_ioctl(avr, AVR_IOCTL_UART_SET_FLAGS('0'), &flags);
    uart_in = avr_io_getirq(avr, AVR_IOCTL_UART_GETIRQ('0'), UART_IRQ_INPUT);
    avr_irq_register_notify(avr_io_getirq(avr, AVR_IOCTL_UART_GETIRQ('0'), UART_IRQ_OUTPUT),
                            on_uart_output, NULL);
    avr_irq_register_notify(avr_io_getirq(avr, AVR_IOCTL_UART_GETIRQ('0'), UART_IRQ_OUT_XON), on_xon, NULL);
    avr_irq_register_notify(avr_io_getirq(avr, AVR_IOCTL_UART_GETIRQ('0'), UART_IRQ_OUT_XOFF), on_xoff, NULL);

    notify('D', 2, on_step);
    notify('D', 3, on_dir);
    notify('D', 4, on_enable);
    notify('B', 2, on_rclk);
    avr_irq_register_notify(avr_io_getirq(avr, AVR_IOCTL_SPI_GETIRQ(0), SPI_IRQ_OUTPUT), on_spi, NULL);

    endstop_pin = avr_io_getirq(avr, AVR_IOCTL_IOPORT_GETIRQ('B'), 0);
    update_endstop();
    avr->sleep = on_sleep;
}

int main(int argc, char *argv[])
{
    elf_firmware_t firmware;
    const char *start = getenv("FIRMWARE_START_STEPS");
    const char *tr = getenv("FIRMWARE_TRACE");
    char *end;

    if (argc != 2) {
        fprintf(stderr, "usage: %s <firmware.elf>\n", argv[0]);
        return 2;
    }
    if (start != NULL && *start != '\0') {
        carriage = strtol(start, &end, 10);
        if (*end != '\0') {
            fprintf(stderr, "rig-simavr: FIRMWARE_START_STEPS=%s is not an integer\n", start);
            return 2;
        }
    }
    trace = tr != NULL && *tr != '\0';
    avr_global_logger_set(logger);

    memset(&firmware, 0, sizeof firmware);
    if (elf_read_firmware(argv[1], &firmware) != 0) {
        fprintf(stderr, "rig-simavr: cannot read %s\n", argv[1]);
        return 1;
    }
    strcpy(firmware.mmcu, "atmega328p");
    firmware.frequency = 16000000;
    avr = avr_make_mcu_by_name(firmware.mmcu);
    if (avr == NULL || avr_init(avr) != 0) {
        fprintf(stderr, "rig-simavr: cannot make an %s\n", firmware.mmcu);
        return 1;
    }
    avr_load_firmware(avr, &firmware);
    wire_up();

    for (;;) {
        int i;

        for (i = 0; i < RUN_BATCH; i++) {
            int state = avr_run(avr);
            if (state == cpu_Done || state == cpu_Crashed) {
                fprintf(stderr, "rig-simavr: firmware %s\n", state == cpu_Done ? "stopped" : "crashed");
                return state == cpu_Done ? 0 : 1;
            }
        }
        read_stdin(0);
        feed_uart();
    }
}
