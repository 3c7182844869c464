/*
 * The hardware interface on a Linux host, for tests and development: the
 * UART is stdin/stdout (raw bytes, unbuffered; give the process one end of a
 * pseudo-terminal or a pipe pair), the carriage and its end stop are
 * simulated. Environment:
 *
 *   FIRMWARE_START_STEPS  Simulated carriage position at start, in steps from
 *                         the end stop (default 2000; unknown to the firmware,
 *                         as after power-up). The end stop is closed at
 *                         positions <= 0 and the carriage moves only while the
 *                         driver is enabled, like the real one.
 *   FIRMWARE_STEP_US      Per-step delay in microseconds instead of the real
 *                         ramp timing (0 = as fast as possible). Unset: the
 *                         real timing (up to 4000 steps/s).
 *   FIRMWARE_TRACE        If set (non-empty), log LED frames and motor
 *                         enable/disable with the simulated carriage position
 *                         to stderr.
 *
 * End of input (the host closed the line) ends the process.
 */
#define _POSIX_C_SOURCE 200809L

#include <errno.h>
#include <poll.h>
#include <stdio.h>
#include <stdlib.h>
#include <time.h>
#include <unistd.h>

#include "hal.h"

static long sim_carriage = 2000;   /* steps from the end stop */
static bool sim_away = true;
static bool sim_enabled;
static long step_us_override = -1;
static bool trace;

static long env_long(const char *name, long fallback, long min, long max)
{
    const char *text = getenv(name);
    char *end;
    long value;

    if (text == NULL || *text == '\0')
        return fallback;
    errno = 0;
    value = strtol(text, &end, 10);
    if (errno != 0 || *end != '\0' || value < min || value > max) {
        fprintf(stderr, "rig-host: %s=%s is not an integer in %ld..%ld\n", name, text, min, max);
        exit(2);
    }
    return value;
}

static void sleep_us(long us)
{
    struct timespec t = { us / 1000000L, (us % 1000000L) * 1000L };

    while (nanosleep(&t, &t) != 0 && errno == EINTR) {
    }
}

void hal_init(void)
{
    const char *tr = getenv("FIRMWARE_TRACE");

    sim_carriage = env_long("FIRMWARE_START_STEPS", sim_carriage, -1000000L, 1000000L);
    step_us_override = env_long("FIRMWARE_STEP_US", -1, 0, 1000000L);
    trace = tr != NULL && *tr != '\0';
}

/* stdin gone (EOF, or EIO on a pty whose other side is closed): power off. */
static void input_closed(void)
{
    exit(0);
}

int hal_uart_read(void)
{
    struct pollfd pfd = { STDIN_FILENO, POLLIN, 0 };
    unsigned char c;
    ssize_t n;

    if (poll(&pfd, 1, 0) <= 0)
        return -1;
    if ((pfd.revents & POLLIN) == 0) {
        if (pfd.revents & (POLLHUP | POLLERR | POLLNVAL))
            input_closed();
        return -1;
    }
    n = read(STDIN_FILENO, &c, 1);
    if (n == 1)
        return c;
    if (n == 0 || (errno != EINTR && errno != EAGAIN))
        input_closed();
    return -1;
}

void hal_uart_write(uint8_t byte)
{
    ssize_t n;

    do {
        n = write(STDOUT_FILENO, &byte, 1);
    } while (n < 0 && errno == EINTR);
    if (n != 1)
        input_closed();   /* the line is gone */
}

void hal_idle(void)
{
    struct pollfd pfd = { STDIN_FILENO, POLLIN, 0 };

    while (poll(&pfd, 1, -1) < 0 && errno == EINTR) {
    }
}

void hal_motor_enable(bool on)
{
    sim_enabled = on;
    if (trace)
        fprintf(stderr, "motor %s carriage=%ld\n", on ? "on" : "off", sim_carriage);
}

void hal_motor_dir(bool away_from_home)
{
    sim_away = away_from_home;
}

void hal_step(void)
{
    if (sim_enabled)   /* a disabled driver ignores STEP */
        sim_carriage += sim_away ? 1 : -1;
}

bool hal_endstop_active(void)
{
    return sim_carriage <= 0;
}

void hal_leds_latch(const uint8_t frame[HAL_LED_FRAME_BYTES])
{
    int i;

    if (!trace)
        return;
    fprintf(stderr, "leds");
    for (i = 0; i < HAL_LED_FRAME_BYTES; i++)
        fprintf(stderr, " %02x", frame[i]);
    fprintf(stderr, "\n");
}

void hal_step_timer_start(void)
{
}

void hal_step_wait(uint16_t interval_us)
{
    long us = step_us_override >= 0 ? step_us_override : (long)interval_us;

    if (us > 0)
        sleep_us(us);
}

void hal_delay_ms(uint16_t ms)
{
    if (step_us_override != 0)   /* FIRMWARE_STEP_US=0: no simulated waiting at all */
        sleep_us(1000L * ms);
}
