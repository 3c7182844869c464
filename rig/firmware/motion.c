/*
 * Step generation. The loop below produces one step per iteration:
 *
 *   poll the host -> wait for the step deadline -> STEP pulse -> next rate
 *
 * The rate follows a constant-acceleration ramp computed per step: with
 * dt = 1 / v, v' = v + a dt = v + a / v. With the step period 1e6 / v that is
 * two 32-bit divisions per step, about 80 us on the ATmega328P at 16 MHz:
 * inside the shortest step period (250 us at 4000 steps/s), and since the
 * HAL waits for deadlines rather than delays it does not slow the steps. The
 * ramp is mirrored for deceleration: a move starts braking when the steps
 * left are no more than the steps it spent accelerating, which also gives a
 * triangular profile for moves too short to reach the top rate.
 */
#include "motion.h"

#include "config.h"
#include "hal.h"

enum until {
    UNTIL_COUNT,            /* exactly `limit` steps, ramped down at the end */
    UNTIL_SWITCH_CLOSED,    /* until the end stop closes, at most `limit` steps */
    UNTIL_SWITCH_OPEN       /* until the end stop opens, at most `limit` steps */
};

struct run {
    bool away;              /* direction */
    int32_t limit;          /* steps */
    uint16_t max_rate;      /* steps/s */
    enum until until;
};

void motion_init(struct motion *m, motion_poll_fn poll, void *poll_ctx)
{
    m->position = 0;
    m->enabled = false;
    m->away = true;
    m->poll = poll;
    m->poll_ctx = poll_ctx;
    hal_motor_enable(false);
    hal_motor_dir(true);
}

void motion_release(struct motion *m)
{
    hal_motor_enable(false);
    m->enabled = false;
}

static void motor_on(struct motion *m)
{
    if (!m->enabled) {
        hal_motor_enable(true);
        hal_delay_ms(MOTOR_ENABLE_SETTLE_MS);
        m->enabled = true;
    }
}

static void set_direction(struct motion *m, bool away)
{
    if (m->away != away) {
        hal_motor_dir(away);   /* the HAL keeps the DIR setup time before the next STEP */
        m->away = away;
    }
}

static uint16_t ramp_up(uint16_t rate, uint16_t max_rate)
{
    uint32_t next = rate + (uint32_t)MOTION_ACCEL / rate;
    return next > max_rate ? max_rate : (uint16_t)next;
}

static uint16_t ramp_down(uint16_t rate, uint16_t min_rate)
{
    uint16_t delta = (uint16_t)((uint32_t)MOTION_ACCEL / rate);
    return rate <= min_rate + delta ? min_rate : (uint16_t)(rate - delta);
}

static uint16_t step_interval_us(uint16_t rate)
{
    return (uint16_t)(1000000UL / rate);   /* rate >= HOME_SLOW_RATE = 200: at most 5000 us */
}

static bool switch_reached(enum until until)
{
    if (until == UNTIL_SWITCH_CLOSED)
        return hal_endstop_active();
    if (until == UNTIL_SWITCH_OPEN)
        return !hal_endstop_active();
    return false;
}

/* One run in one direction; see enum until for when it ends. */
static enum motion_result run(struct motion *m, const struct run *r)
{
    uint16_t min_rate = r->max_rate < MOTION_START_RATE ? r->max_rate : MOTION_START_RATE;
    uint16_t rate = min_rate;
    int32_t done = 0;
    int32_t ramp_steps = 0;   /* steps spent accelerating so far */

    motor_on(m);
    set_direction(m, r->away);
    hal_step_timer_start();
    while (done < r->limit) {
        if (switch_reached(r->until))
            return MOTION_DONE;
        if (m->poll(m->poll_ctx))
            return MOTION_ABORTED;
        hal_step_wait(step_interval_us(rate));
        hal_step();
        m->position += r->away ? 1 : -1;
        done++;
        if (r->until == UNTIL_COUNT && r->limit - done <= ramp_steps) {
            rate = ramp_down(rate, min_rate);
        } else if (rate < r->max_rate) {
            rate = ramp_up(rate, r->max_rate);
            ramp_steps++;
        }
    }
    if (r->until == UNTIL_COUNT)
        return MOTION_DONE;
    return switch_reached(r->until) ? MOTION_DONE : MOTION_NO_SWITCH;
}

enum motion_result motion_move_to(struct motion *m, int32_t target)
{
    int32_t delta = target - m->position;
    struct run r = { delta > 0, delta > 0 ? delta : -delta, MOTION_MAX_RATE, UNTIL_COUNT };

    if (delta == 0)
        return MOTION_DONE;
    return run(m, &r);
}

/*
 * Homing. A mechanical switch bounces for a few milliseconds when it closes or
 * opens; each phase acts on the first reading that reaches its condition and
 * the phases are separated by at least HOME_BACKOFF_STEPS, so bounce cannot
 * end a phase early: zero is where the switch first closes on the slow
 * approach.
 */
enum motion_result motion_home(struct motion *m)
{
    const struct run leave = { true, HOME_RELEASE_LIMIT, HOME_SLOW_RATE, UNTIL_SWITCH_OPEN };
    const struct run seek = { false, HOME_SEARCH_LIMIT, HOME_FAST_RATE, UNTIL_SWITCH_CLOSED };
    const struct run backoff = { true, HOME_BACKOFF_STEPS, HOME_SLOW_RATE, UNTIL_COUNT };
    const struct run touch = { false, HOME_BACKOFF_STEPS + HOME_RELEASE_LIMIT, HOME_SLOW_RATE,
                               UNTIL_SWITCH_CLOSED };
    enum motion_result res;

    if (hal_endstop_active()) {   /* already on the switch: get off it first */
        res = run(m, &leave);
        if (res != MOTION_DONE)
            return res;
    }
    res = run(m, &seek);
    if (res == MOTION_DONE)
        res = run(m, &leave);
    if (res == MOTION_DONE)
        res = run(m, &backoff);
    if (res == MOTION_DONE)
        res = run(m, &touch);
    if (res == MOTION_DONE)
        m->position = 0;
    return res;
}
