/*
 * Constant strings in program memory. On the AVR (Harvard architecture)
 * string literals would otherwise be copied into the 2 KB of RAM at start-up;
 * FSTR() keeps them in flash and flash_char() reads one byte back. On the
 * host both are plain C.
 */
#ifndef FACETSYNTH_RIG_PGM_H
#define FACETSYNTH_RIG_PGM_H

#ifdef __AVR__
#include <avr/pgmspace.h>
#define FSTR(s) PSTR(s)
static inline char flash_char(const char *p) { return (char)pgm_read_byte(p); }
#else
#define FSTR(s) (s)
static inline char flash_char(const char *p) { return *p; }
#endif

#endif
