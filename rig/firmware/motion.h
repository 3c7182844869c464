/*
 * Carriage motion: absolute moves with a trapezoidal (or, for short moves,
 * triangular) speed profile, and homing against the end stop. Blocking: the
 * functions return when the motion has ended. Between two steps they call the
 * poll function given to motion_init(); if it returns true the motion aborts
 * at once (emergency stop, no deceleration).
 */
#ifndef FACETSYNTH_RIG_MOTION_H
#define FACETSYNTH_RIG_MOTION_H

#include <stdbool.h>
#include <stdint.h>

typedef bool (*motion_poll_fn)(void *ctx);

enum motion_result {
    MOTION_DONE,        /* target or switch reached */
    MOTION_ABORTED,     /* the poll function asked to stop */
    MOTION_NO_SWITCH    /* homing: the end stop did not close (or open) within its limit */
};

struct motion {
    int32_t position;   /* steps from the home end stop; meaningful once homed */
    bool enabled;       /* driver outputs on */
    bool away;          /* current direction: true = steps increase */
    motion_poll_fn poll;
    void *poll_ctx;
};

void motion_init(struct motion *m, motion_poll_fn poll, void *poll_ctx);

/* Drive to absolute position target (caller checks the range and homing). */
enum motion_result motion_move_to(struct motion *m, int32_t target);

/* Find the end stop; on MOTION_DONE the position is 0 there. */
enum motion_result motion_home(struct motion *m);

/* Disable the driver outputs (the carriage may then be moved by hand). */
void motion_release(struct motion *m);

#endif
