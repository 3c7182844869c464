/*
 * The rig controller's line protocol (rig/PROTOCOL.md, version 2): line
 * assembly, parsing, the controller state machine, replies and the
 * sequence-number replay. Portable C: all I/O goes through hal.h, all memory
 * is in struct proto (no dynamic allocation).
 */
#ifndef FACETSYNTH_RIG_PROTOCOL_H
#define FACETSYNTH_RIG_PROTOCOL_H

#include <stdbool.h>
#include <stdint.h>

#include "motion.h"

#define PROTO_LINE_MAX 64     /* longest command line in bytes, '\n' included */
#define PROTO_REPLY_MAX 128   /* longest reply line in bytes, '\n' included */
#define PROTO_SEQ_DIGITS 4    /* @<n>: 1 to 4 decimal digits, 0..9999 */

enum proto_error {
    ERR_UNKNOWN_COMMAND = 1,
    ERR_BAD_ARGUMENT = 2,
    ERR_OUT_OF_RANGE = 3,
    ERR_NOT_HOMED = 4,
    ERR_STOPPED = 5
};

/* A command line being received: at most PROTO_LINE_MAX - 1 bytes before '\n'. */
struct proto_line {
    char text[PROTO_LINE_MAX];   /* the line, NUL-terminated once complete */
    uint8_t len;
    uint8_t mode;                /* enum line_mode (protocol.c) */
};

/* A reply without its '\n': at most PROTO_REPLY_MAX - 1 bytes. */
struct proto_reply {
    char text[PROTO_REPLY_MAX - 1];
    uint8_t len;
};

struct proto {
    struct proto_line line;          /* commands, between motions */
    struct proto_line motion_line;   /* bytes arriving during a motion: only STOP counts */
    bool stop_pending;               /* motion_line holds a STOP that aborted a motion */

    bool homed;
    int8_t lit;                      /* lit LED, -1 = all off */
    struct motion motion;

    struct proto_reply reply;        /* the reply being built */
    struct proto_reply stored;       /* reply to the last prefixed command */
    uint16_t stored_seq;
    bool stored_valid;               /* false after reset */
};

/* Power-on state: not homed, LEDs off, motor released, no stored reply. */
void proto_init(struct proto *p);

/* Process one received byte; executes and answers a command on its '\n'. */
void proto_feed(struct proto *p, uint8_t byte);

#endif
