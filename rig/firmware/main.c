/*
 * Rig controller firmware: feed every received byte to the protocol, sleep
 * when there is nothing to do. Commands run to completion inside
 * proto_feed() (a HOME or MOVE returns when the motion has ended), so this
 * loop is all there is; the only interrupt is the UART receiver (hal_avr.c).
 */
#include "hal.h"
#include "protocol.h"

int main(void)
{
    static struct proto proto;   /* static: its size is known at link time (avr-size) */
    int c;

    hal_init();
    proto_init(&proto);
    for (;;) {
        while ((c = hal_uart_read()) >= 0)
            proto_feed(&proto, (uint8_t)c);
        hal_idle();
    }
}
