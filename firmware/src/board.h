/*
 * Pins and constants of the galvo board: an Arduino Mega 2560 (ATmega2560, 16 MHz) driving
 * an AD5754R quad 16-bit +-10 V DAC on its hardware SPI. docs/hardware.md has the wiring.
 *
 *   signal            AVR pin  Mega pin  direction
 *   DAC SCLK          PB1      D52       out (SPI mode 2: idles high, data taken on the falling edge)
 *   DAC SDIN          PB2      D51       out (MOSI)
 *   (SPI SS)          PB0      D53       out, unconnected: an output keeps the SPI a master
 *   DAC /SYNC         PL0      D49       out, idle high
 *   DAC /LDAC         PL1      D48       out, idle high; a low pulse moves all four input
 *                                        registers to the outputs at once
 *   camera trigger    PB5      D11       out, OC1A: set and cleared by Timer1's compare unit
 *   laser enable      PA0      D22       out, high = laser on; low from reset (needs an
 *                                        external 10 kohm pull-down for the reset interval)
 *   interlock         PE4      D2        in, pull-up, INT4; closed loop to GND = OK,
 *                                        open (high) = laser off, galvos parked, FAULT
 *
 * /SYNC and /LDAC sit on port L so that nothing writes PORTB while a scan runs: the trigger
 * pin belongs to the compare unit then.
 */
#ifndef GALVO_BOARD_H
#define GALVO_BOARD_H

#include <avr/io.h>

#define PIN_SS PB0
#define PIN_SYNC PL0
#define PIN_SCK PB1
#define PIN_MOSI PB2
#define PIN_LDAC PL1
#define PIN_TRIG PB5
#define PIN_LASER PA0
#define PIN_INTERLOCK PE4

/* UART0 (the Mega's USB bridge): 1 Mbaud, 8N1. 16 MHz / (8 * (1 + 1)) with U2X, exact. */
#define UART_UBRR 1

/* Timer1 runs free at F_CPU / 8 = 2 MHz: the board clock (0.5 us ticks) and, through its
 * compare units A (trigger pin) and B (/LDAC slot), the scan timing. */
#define TICKS_PER_US 2u
/* Trigger pulse width [ticks]: 20 us. */
#define PULSE_TICKS 40u

/* Protocol parameters reported in BoardInfo (docs/board-protocol.md). */
#define FIRMWARE_ID "galvoscan-m2560"
#define MAX_SCAN_ROWS 768u
#define MIN_PERIOD_US 500u
#define MAX_PERIOD_US 60000000ul
/* Heartbeat watchdog: 150 ms without a valid host packet. */
#define WATCHDOG_TICKS (150000ul * TICKS_PER_US)

#endif
