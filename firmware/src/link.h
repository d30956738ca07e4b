/*
 * Byte link to the host: UART0 with interrupt-driven ring buffers, COBS framing and CRC-32,
 * as docs/board-protocol.md defines them.
 */
#ifndef GALVO_LINK_H
#define GALVO_LINK_H

#include <stdint.h>

/* Longest COBS frame a receiver accepts (without its 0x00 delimiter) [bytes]. */
#define MAX_ENCODED_FRAME 256u
#define HEADER_SIZE 3u
#define CRC_SIZE 4u
#define MAX_PAYLOAD 240u
#define MAX_PACKET (HEADER_SIZE + MAX_PAYLOAD + CRC_SIZE)

void link_init(void);
/* Next received byte, or -1 if none is waiting. */
int16_t link_getc(void);
/* 1 if a received byte is waiting. */
uint8_t link_rx_pending(void);
/* Queue bytes for transmission; waits while the transmit ring is full. */
void link_write(const uint8_t *data, uint16_t n);

uint32_t crc32_update(uint32_t crc, const uint8_t *data, uint16_t n);
/* CRC-32/ISO-HDLC (zlib's crc32) of n bytes. */
uint32_t crc32(const uint8_t *data, uint16_t n);

/* COBS-decode data[0..n) in place; returns the decoded length or -1 (zero byte inside, or a
 * block running past the end). */
int16_t cobs_decode_inplace(uint8_t *data, uint16_t n);
/* COBS-encode src[0..n) into dst (room for n + n / 254 + 1 bytes); returns its length. */
uint16_t cobs_encode(const uint8_t *src, uint16_t n, uint8_t *dst);

#endif
