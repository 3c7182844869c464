/*
 * Rig configuration of the reference build (Wang et al. 2008, sec. 4):
 * 40 LEDs at 6.0 mm pitch on a carriage with 300 mm of travel, driven by a
 * 1.8 degree NEMA 17 motor at 1/16 microstepping and a GT2 belt on a
 * 20-tooth pulley (40 mm per revolution): 3200 / 40 = 80 steps per mm.
 *
 * These values are what ID? reports; the host's rig description (the YAML
 * files in rig/descriptions/) must agree with them.
 */
#ifndef FACETSYNTH_RIG_CONFIG_H
#define FACETSYNTH_RIG_CONFIG_H

#define FW_VERSION "1.0.0"          /* ID? version token: no spaces */
#define PROTO_VERSION_TEXT "2"      /* ID? PROTO= field: rig/PROTOCOL.md version */

#define RIG_N_LEDS 40               /* LEDs = outputs of the 74HC595 chain */
#define RIG_MAX_STEPS 24000L        /* full travel: 300 mm at 80 steps/mm */
#define RIG_STEPS_PER_MM_TEXT "80"  /* reported as is, a decimal number */

/*
 * Motion profile, in (micro)steps and seconds. The start rate is below the
 * motor's pull-in rate, so it can start and stop there without a ramp; the
 * ramp between it and the top rate has constant acceleration.
 */
#define MOTION_START_RATE 400u      /* steps/s  (5 mm/s)   */
#define MOTION_MAX_RATE 4000u       /* steps/s  (50 mm/s)  */
#define MOTION_ACCEL 16000u         /* steps/s^2 (200 mm/s^2): ~500 steps to full speed */

/*
 * Homing: approach the end stop at HOME_FAST_RATE (ramped), back off until it
 * opens plus HOME_BACKOFF_STEPS, then re-approach at HOME_SLOW_RATE (no ramp)
 * so that step 0 is where the switch closes at a slow, repeatable speed.
 */
#define HOME_FAST_RATE 2000u        /* steps/s  (25 mm/s)  */
#define HOME_SLOW_RATE 200u         /* steps/s  (2.5 mm/s) */
#define HOME_BACKOFF_STEPS 160L     /* 2 mm */
#define HOME_RELEASE_LIMIT 800L     /* 10 mm: the switch must open within this when backing off */
#define HOME_SEARCH_LIMIT (RIG_MAX_STEPS + RIG_MAX_STEPS / 10)   /* full travel + 10 % */

#define MOTOR_ENABLE_SETTLE_MS 2u   /* driver outputs settle after EN (A4988: ~1 ms, TMC2209 similar) */

#endif
