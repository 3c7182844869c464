#!/usr/bin/env bash
# Debian's AVR toolchain and simavr for the firmware test (make test-firmware), installed only when missing.
# rig/firmware/Makefile itself installs nothing.
set -euo pipefail
needed=()
command -v avr-gcc >/dev/null 2>&1 || needed+=(gcc-avr binutils-avr)
[ -f /usr/lib/avr/include/avr/io.h ] || needed+=(avr-libc)
[ -f /usr/include/simavr/sim_avr.h ] || needed+=(simavr libsimavr-dev)
if [ ${#needed[@]} -gt 0 ]; then
    echo "installing ${needed[*]}"
    apt-get update -qq
    DEBIAN_FRONTEND=noninteractive apt-get install -y -qq "${needed[@]}" >/dev/null
fi
