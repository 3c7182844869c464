/*
 * The controller side of rig/PROTOCOL.md (version 2). The Python emulator
 * (src/facetsynth/rig/emulator.py) implements the same document;
 * tests/test_rig_conformance.py holds both to the same replies, so the
 * messages below are spelled exactly as the emulator spells them.
 */
#include "protocol.h"

#include <stddef.h>

#include "config.h"
#include "hal.h"
#include "pgm.h"

#define MAX_WORDS 3   /* verb + 2 arguments: enough to reject every wrong arity */

enum line_mode {
    LINE_COLLECT,           /* storing bytes */
    LINE_DISCARD_TOO_LONG,  /* over the limit: drop up to '\n', then ERR 2 */
    LINE_DISCARD_SILENT     /* began during a motion: drop up to '\n', no reply */
};

enum line_event { LINE_NONE, LINE_READY, LINE_TOO_LONG };

/* --- line assembly --------------------------------------------------------- */

static void line_reset(struct proto_line *l)
{
    l->len = 0;
    l->mode = LINE_COLLECT;
    l->text[0] = '\0';
}

static bool line_partial(const struct proto_line *l)
{
    return l->len > 0 || l->mode != LINE_COLLECT;
}

/*
 * Add one byte. On '\n' a collected line is NUL-terminated in place (one '\r'
 * before the '\n' removed) and stays valid until the next byte is added.
 */
static enum line_event line_feed(struct proto_line *l, uint8_t c)
{
    enum line_event ev;

    if (c == '\n') {
        if (l->mode == LINE_COLLECT) {
            if (l->len > 0 && l->text[l->len - 1] == '\r')
                l->len--;
            l->text[l->len] = '\0';
            ev = LINE_READY;
        } else {
            ev = l->mode == LINE_DISCARD_TOO_LONG ? LINE_TOO_LONG : LINE_NONE;
        }
        l->len = 0;
        l->mode = LINE_COLLECT;
        return ev;
    }
    if (l->mode != LINE_COLLECT)
        return LINE_NONE;
    if (l->len >= PROTO_LINE_MAX - 1) {   /* this byte would leave no room for '\n' */
        l->mode = LINE_DISCARD_TOO_LONG;
        return LINE_NONE;
    }
    /* A NUL would end the C string early; 0x7F is as invalid in every token. */
    l->text[l->len++] = c == '\0' ? (char)0x7F : (char)c;
    return LINE_NONE;
}

/* --- parsing ---------------------------------------------------------------- */

static bool is_digit(char c)
{
    return c >= '0' && c <= '9';
}

static const char *skip_spaces(const char *s)
{
    while (*s == ' ')
        s++;
    return s;
}

/* Whether a RAM word equals a flash string. */
static bool word_is(const char *word, const char *flash)
{
    char c;

    while ((c = flash_char(flash++)) != '\0') {
        if (*word++ != c)
            return false;
    }
    return *word == '\0';
}

/*
 * A sequence prefix "@<n>" at s, 1 to 4 digits followed by a space or the end
 * of the line. Returns the characters used, or 0 if it is malformed.
 */
static uint8_t parse_seq(const char *s, uint16_t *seq)
{
    uint8_t n = 1;
    uint16_t value = 0;

    if (s[0] != '@')
        return 0;
    while (is_digit(s[n])) {
        if (n > PROTO_SEQ_DIGITS)
            return 0;
        value = (uint16_t)(value * 10u + (uint16_t)(s[n] - '0'));
        n++;
    }
    if (n == 1 || (s[n] != ' ' && s[n] != '\0'))
        return 0;
    *seq = value;
    return n;
}

/*
 * A protocol integer: optional '-', then one or more decimal digits. Values of
 * magnitude 1e9 and more are clamped to 1e9, which is out of every range here.
 */
static bool parse_int(const char *s, int32_t *out)
{
    bool negative = false;
    uint32_t magnitude = 0;

    if (*s == '-') {
        negative = true;
        s++;
    }
    if (*s == '\0')
        return false;
    for (; *s != '\0'; s++) {
        if (!is_digit(*s))
            return false;
        if (magnitude < 100000000UL)
            magnitude = magnitude * 10u + (uint32_t)(*s - '0');
        else
            magnitude = 1000000000UL;
    }
    *out = negative ? -(int32_t)magnitude : (int32_t)magnitude;
    return true;
}

/*
 * Split s into words at spaces, in place. Stores the first `max` words in
 * words[] and returns how many there are in all (so that a command with too
 * many arguments is recognised as such).
 */
static uint8_t split_words(char *s, char *words[], uint8_t max)
{
    uint8_t count = 0;

    for (;;) {
        while (*s == ' ')
            s++;
        if (*s == '\0')
            return count;
        if (count < max)
            words[count] = s;
        count++;
        while (*s != ' ' && *s != '\0')
            s++;
        if (*s == ' ')
            *s++ = '\0';
    }
}

/* Whether a complete line is a valid STOP command, with or without a valid prefix. */
static bool is_stop_line(const char *text)
{
    const char *s = skip_spaces(text);
    uint16_t seq;

    if (*s == '@') {
        uint8_t used = parse_seq(s, &seq);
        if (used == 0)
            return false;
        s = skip_spaces(s + used);
    }
    if (s[0] != 'S' || s[1] != 'T' || s[2] != 'O' || s[3] != 'P')
        return false;
    return *skip_spaces(s + 4) == '\0';
}

/* --- replies ---------------------------------------------------------------- */

static void reply_char(struct proto_reply *r, char c)
{
    if (r->len < sizeof r->text)   /* never reached by the replies below; keeps the bound */
        r->text[r->len++] = c;
}

static void reply_fstr(struct proto_reply *r, const char *flash)
{
    char c;

    while ((c = flash_char(flash++)) != '\0')
        reply_char(r, c);
}

static void reply_int(struct proto_reply *r, int32_t value)
{
    char digits[10];
    uint8_t n = 0;
    uint32_t magnitude = value < 0 ? (uint32_t)0 - (uint32_t)value : (uint32_t)value;

    if (value < 0)
        reply_char(r, '-');
    do {
        digits[n++] = (char)('0' + magnitude % 10u);
        magnitude /= 10u;
    } while (magnitude != 0);
    while (n > 0)
        reply_char(r, digits[--n]);
}

static void reply_err(struct proto_reply *r, enum proto_error code, const char *flash_message)
{
    reply_fstr(r, FSTR("ERR "));
    reply_char(r, (char)('0' + code));
    reply_char(r, ' ');
    reply_fstr(r, flash_message);
}

static void reply_send(const struct proto_reply *r)
{
    uint8_t i;

    for (i = 0; i < r->len; i++)
        hal_uart_write((uint8_t)r->text[i]);
    hal_uart_write('\n');
}

/* --- controller state ------------------------------------------------------- */

static void leds_show(int8_t lit)
{
    uint8_t frame[HAL_LED_FRAME_BYTES] = { 0 };

    if (lit >= 0)
        frame[lit / 8] = (uint8_t)(1u << (lit % 8));
    hal_leds_latch(frame);
}

/* Everything STOP does: LEDs off, motor released, position no longer trusted. */
static void emergency_stop(struct proto *p)
{
    motion_release(&p->motion);
    p->homed = false;
    p->lit = -1;
    leds_show(-1);
}

/*
 * Poll function of the motion: reads what arrived during the motion into
 * motion_line and aborts on a STOP line. Every other line is dropped.
 */
static bool poll_for_stop(void *ctx)
{
    struct proto *p = ctx;
    int c;

    while ((c = hal_uart_read()) >= 0) {
        if (line_feed(&p->motion_line, (uint8_t)c) == LINE_READY && is_stop_line(p->motion_line.text)) {
            p->stop_pending = true;
            return true;
        }
    }
    return false;
}

/* The reply to a HOME or MOVE once its motion has ended. */
static void finish_motion(struct proto *p, enum motion_result result)
{
    if (result == MOTION_DONE) {
        reply_fstr(&p->reply, FSTR("OK POS "));
        reply_int(&p->reply, p->motion.position);
    } else {
        motion_release(&p->motion);
        p->homed = false;
        if (result == MOTION_ABORTED)
            reply_err(&p->reply, ERR_STOPPED, FSTR("STOPPED"));
        else
            reply_err(&p->reply, ERR_NOT_HOMED, FSTR("HOME SWITCH NOT FOUND"));
    }
    /* A line that began during the motion is dropped, also the part still to come. */
    if (!p->stop_pending) {
        if (line_partial(&p->motion_line))
            p->line.mode = LINE_DISCARD_SILENT;
        line_reset(&p->motion_line);
    }
}

/* --- commands ----------------------------------------------------------------- */

static bool no_args(struct proto *p, uint8_t nargs)
{
    if (nargs == 0)
        return true;
    reply_err(&p->reply, ERR_BAD_ARGUMENT, FSTR("UNEXPECTED ARGUMENT"));
    return false;
}

static void cmd_identify(struct proto *p, uint8_t nargs)
{
    if (!no_args(p, nargs))
        return;
    reply_fstr(&p->reply, FSTR("OK FACETSYNTH-RIG " FW_VERSION " LEDS="));
    reply_int(&p->reply, RIG_N_LEDS);
    reply_fstr(&p->reply, FSTR(" STEPS="));
    reply_int(&p->reply, RIG_MAX_STEPS);
    reply_fstr(&p->reply, FSTR(" STEPS_PER_MM=" RIG_STEPS_PER_MM_TEXT " PROTO=" PROTO_VERSION_TEXT));
}

static void cmd_home(struct proto *p, uint8_t nargs)
{
    enum motion_result result;

    if (!no_args(p, nargs))
        return;
    p->homed = false;   /* the position is in flux until the switch is found */
    result = motion_home(&p->motion);
    p->homed = result == MOTION_DONE;
    finish_motion(p, result);
}

static void cmd_move(struct proto *p, uint8_t nargs, char *args[])
{
    int32_t target;

    if (nargs != 1 || !parse_int(args[0], &target)) {
        reply_err(&p->reply, ERR_BAD_ARGUMENT, FSTR("EXPECTED MOVE <steps>"));
    } else if (!p->homed) {
        reply_err(&p->reply, ERR_NOT_HOMED, FSTR("NOT HOMED"));
    } else if (target < 0 || target > RIG_MAX_STEPS) {
        reply_err(&p->reply, ERR_OUT_OF_RANGE, FSTR("POSITION OUT OF RANGE 0.."));
        reply_int(&p->reply, RIG_MAX_STEPS);
    } else {
        finish_motion(p, motion_move_to(&p->motion, target));
    }
}

static void cmd_position(struct proto *p, uint8_t nargs)
{
    if (!no_args(p, nargs))
        return;
    if (!p->homed) {
        reply_err(&p->reply, ERR_NOT_HOMED, FSTR("NOT HOMED"));
        return;
    }
    reply_fstr(&p->reply, FSTR("OK POS "));
    reply_int(&p->reply, p->motion.position);
}

static void reply_led_state(struct proto *p)
{
    reply_fstr(&p->reply, FSTR("OK LED "));
    if (p->lit < 0)
        reply_fstr(&p->reply, FSTR("OFF"));
    else
        reply_int(&p->reply, p->lit);
}

static void cmd_led(struct proto *p, uint8_t nargs, char *args[])
{
    int32_t index;

    if (nargs == 1 && word_is(args[0], FSTR("OFF"))) {
        index = -1;
    } else if (nargs != 1 || !parse_int(args[0], &index)) {
        reply_err(&p->reply, ERR_BAD_ARGUMENT, FSTR("EXPECTED LED <index>|OFF"));
        return;
    } else if (index < 0 || index >= RIG_N_LEDS) {
        reply_err(&p->reply, ERR_OUT_OF_RANGE, FSTR("LED INDEX OUT OF RANGE 0.."));
        reply_int(&p->reply, RIG_N_LEDS - 1);
        return;
    }
    p->lit = (int8_t)index;
    leds_show(p->lit);
    reply_led_state(p);
}

static void cmd_lit_led(struct proto *p, uint8_t nargs)
{
    if (no_args(p, nargs))
        reply_led_state(p);
}

static void cmd_stop(struct proto *p, uint8_t nargs)
{
    if (!no_args(p, nargs))
        return;
    emergency_stop(p);
    reply_fstr(&p->reply, FSTR("OK STOP"));
}

/* Error precedence 1, 2, 4, 3: unknown verb first, then each handler's order. */
static void dispatch(struct proto *p, uint8_t nwords, char *words[])
{
    uint8_t nargs;
    const char *verb;

    if (nwords == 0) {
        reply_err(&p->reply, ERR_UNKNOWN_COMMAND, FSTR("EMPTY COMMAND"));
        return;
    }
    verb = words[0];
    nargs = (uint8_t)(nwords - 1);
    if (word_is(verb, FSTR("ID?")))
        cmd_identify(p, nargs);
    else if (word_is(verb, FSTR("HOME")))
        cmd_home(p, nargs);
    else if (word_is(verb, FSTR("MOVE")))
        cmd_move(p, nargs, words + 1);
    else if (word_is(verb, FSTR("POS?")))
        cmd_position(p, nargs);
    else if (word_is(verb, FSTR("LED")))
        cmd_led(p, nargs, words + 1);
    else if (word_is(verb, FSTR("LED?")))
        cmd_lit_led(p, nargs);
    else if (word_is(verb, FSTR("STOP")))
        cmd_stop(p, nargs);
    else
        reply_err(&p->reply, ERR_UNKNOWN_COMMAND, FSTR("UNKNOWN COMMAND"));
}

/* --- one line ------------------------------------------------------------------ */

static void reply_begin(struct proto *p, bool has_seq, uint16_t seq)
{
    p->reply.len = 0;
    if (has_seq) {
        reply_char(&p->reply, '@');
        reply_int(&p->reply, seq);
        reply_char(&p->reply, ' ');
    }
}

/* Execute one complete line (modified in place) and send its reply. */
static void execute(struct proto *p, char *line)
{
    char *s = line;
    char *words[MAX_WORDS];
    uint8_t nwords;
    uint16_t seq = 0;
    bool has_seq = false;

    while (*s == ' ')
        s++;
    if (*s == '\0')
        return;   /* blank line: no reply */
    if (*s == '@') {
        uint8_t used = parse_seq(s, &seq);
        if (used == 0) {
            reply_begin(p, false, 0);
            reply_err(&p->reply, ERR_BAD_ARGUMENT, FSTR("BAD SEQUENCE NUMBER"));
            reply_send(&p->reply);
            return;
        }
        has_seq = true;
        s += used;
    }
    nwords = split_words(s, words, MAX_WORDS);
    if (has_seq && p->stored_valid && seq == p->stored_seq
        && !(nwords > 0 && word_is(words[0], FSTR("STOP")))) {
        reply_send(&p->stored);   /* a retry: the same reply, nothing executed */
        return;
    }
    reply_begin(p, has_seq, seq);
    dispatch(p, nwords, words);
    reply_send(&p->reply);
    if (has_seq) {
        p->stored = p->reply;
        p->stored_seq = seq;
        p->stored_valid = true;
    }
}

/* --- public ---------------------------------------------------------------------- */

void proto_init(struct proto *p)
{
    line_reset(&p->line);
    line_reset(&p->motion_line);
    p->stop_pending = false;
    p->homed = false;
    p->lit = -1;
    p->reply.len = 0;
    p->stored.len = 0;
    p->stored_seq = 0;
    p->stored_valid = false;
    motion_init(&p->motion, poll_for_stop, p);
    leds_show(-1);
}

void proto_feed(struct proto *p, uint8_t byte)
{
    switch (line_feed(&p->line, byte)) {
    case LINE_READY:
        execute(p, p->line.text);
        break;
    case LINE_TOO_LONG:
        reply_begin(p, false, 0);
        reply_err(&p->reply, ERR_BAD_ARGUMENT, FSTR("LINE TOO LONG"));
        reply_send(&p->reply);
        break;
    case LINE_NONE:
        break;
    }
    if (p->stop_pending) {   /* a STOP aborted the motion just answered: answer it too */
        p->stop_pending = false;
        execute(p, p->motion_line.text);
        line_reset(&p->motion_line);
    }
}
