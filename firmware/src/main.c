/*
 * galvoscan galvo board firmware: ATmega2560 (Arduino Mega 2560) + AD5754R.
 *
 * Speaks the board protocol of docs/board-protocol.md (protocol version 1) on UART0.
 *
 * Timing (all from Timer1, free-running at 2 MHz, which is also the board clock):
 *   - Scan rows are loaded ahead into the DAC's input registers; a /LDAC pulse half a
 *     period before each trigger edge moves them to the outputs, so each edge fires on
 *     codes already in the outputs (and the galvos have had half a period to settle).
 *   - The camera trigger is the OC1A pin, set and cleared by the compare unit's hardware:
 *     the edge time is the compare value, without interrupt latency.
 *   - The compare interrupts only queue a small record per trigger; CRC, COBS and the
 *     UART are the main loop's work.
 * Safety:
 *   - the laser-enable pin is driven low before anything else runs (.init3);
 *   - no valid host packet for 150 ms: scan stopped, all channels to 0 V, laser off,
 *     FAULT WATCHDOG and STATUS;
 *   - interlock open (INT4): laser off in the interrupt, then the scan stopped, the galvos
 *     parked at 0 V and FAULT INTERLOCK sent; laser and output commands are refused while
 *     it stays open.
 */
#include <avr/eeprom.h>
#include <avr/interrupt.h>
#include <avr/io.h>
#include <avr/sleep.h>
#include <string.h>

#include "board.h"
#include "link.h"

/* ---- protocol constants (docs/board-protocol.md) ---------------------------------- */
#define PROTOCOL_VERSION 1u
enum {
    T_HELLO = 0x01, T_HEARTBEAT, T_SET_VOLTS, T_LASER, T_SCAN_BEGIN, T_SCAN_DATA,
    T_SCAN_START, T_SCAN_STOP, T_SAFE, T_GET_STATUS,
    T_ACK = 0x80, T_NAK, T_EVENT, T_BOOT, T_STATUS, T_FAULT
};
enum {
    NAK_BAD_MESSAGE = 1, NAK_NO_SESSION, NAK_VERSION, NAK_BUSY, NAK_BAD_ARGUMENT,
    NAK_TABLE_MISMATCH, NAK_INTERLOCK
};
enum { STATE_IDLE = 0, STATE_LOADED, STATE_SCANNING, STATE_DONE };
enum { FAULT_WATCHDOG = 1, FAULT_OVERRUN = 2, FAULT_INTERLOCK = 3 };
#define FLAG_WATCHDOG 0x01
#define FLAG_INTERLOCK 0x02
#define CODE_ZERO 32768u
#define ROWS_PER_CHUNK 29u

/* ---- laser off before the C runtime starts ---------------------------------------- */
void laser_off_at_reset(void) __attribute__((naked, used, section(".init3")));
void laser_off_at_reset(void)
{
    PORTA &= ~_BV(PIN_LASER);
    DDRA |= _BV(PIN_LASER);
}

static inline void laser_set(uint8_t on)
{
    if (on)
        PORTA |= _BV(PIN_LASER);
    else
        PORTA &= ~_BV(PIN_LASER);
}

static inline uint8_t laser_is_on(void) { return (PORTA & _BV(PIN_LASER)) != 0; }
static inline uint8_t interlock_open(void) { return (PINE & _BV(PIN_INTERLOCK)) != 0; }

/* ---- board clock: Timer1 at 2 MHz, extended by its overflow count ----------------- */
static volatile uint32_t clock_hi;

ISR(TIMER1_OVF_vect) { clock_hi++; }

/* Board clock [ticks of 0.5 us]; callable with interrupts on or off. */
static uint64_t now_ticks(void)
{
    uint8_t sreg = SREG;
    cli();
    uint16_t lo = TCNT1;
    uint32_t hi = clock_hi;
    if ((TIFR1 & _BV(TOV1)) && lo < 0x8000u)
        hi++; /* the overflow happened but its interrupt has not run yet */
    SREG = sreg;
    return ((uint64_t)hi << 16) | lo;
}

static inline uint64_t ticks_to_us(uint64_t t) { return t / TICKS_PER_US; }

static volatile uint16_t out_codes[4]; /* what the DAC outputs now */

/* ---- AD5754R on SPI ---------------------------------------------------------------- */
static uint8_t spi_xfer(uint8_t b)
{
    SPDR = b;
    while (!(SPSR & _BV(SPIF)))
        ;
    return SPDR;
}

/* One 24-bit word: R/W, 0, REG[2:0], A[2:0] in the first byte, then 16 data bits. */
static void dac_word(uint8_t head, uint16_t data)
{
    PORTL &= ~_BV(PIN_SYNC);
    spi_xfer(head);
    spi_xfer((uint8_t)(data >> 8));
    spi_xfer((uint8_t)data);
    PORTL |= _BV(PIN_SYNC);
}

/* Four codes into the DAC's input registers (the outputs do not change). Codes are offset
 * binary (BIN/2sCOMP tied low): 32768 = 0 V. */
static void dac_load(const uint16_t *codes)
{
    for (uint8_t ch = 0; ch < 4; ch++)
        dac_word(ch, codes[ch]);
}

static inline void dac_ldac(void)
{
    PORTL &= ~_BV(PIN_LDAC);
    __asm__ __volatile__("nop\n\tnop");
    PORTL |= _BV(PIN_LDAC);
}

static void dac_init(void)
{
    PORTL |= _BV(PIN_SYNC) | _BV(PIN_LDAC);
    DDRL |= _BV(PIN_SYNC) | _BV(PIN_LDAC);
    PORTB |= _BV(PIN_SCK);
    PORTB &= ~_BV(PIN_TRIG);
    DDRB |= _BV(PIN_SS) | _BV(PIN_SCK) | _BV(PIN_MOSI) | _BV(PIN_TRIG);
    /* master, mode 2 (CPOL = 1, CPHA = 0), F_CPU / 2 = 8 MHz (the DAC takes 30 MHz) */
    SPCR = _BV(SPE) | _BV(MSTR) | _BV(CPOL);
    SPSR = _BV(SPI2X);
    dac_word(0x0C, 0x0004); /* output range, all channels: +-10 V */
    static const uint16_t zero[4] = {CODE_ZERO, CODE_ZERO, CODE_ZERO, CODE_ZERO};
    dac_load(zero);
    dac_ldac();             /* 0 V in the DAC registers before the outputs power up */
    for (uint8_t ch = 0; ch < 4; ch++)
        out_codes[ch] = CODE_ZERO;
    dac_word(0x10, 0x001F); /* power control: internal reference and channels A-D up */
}

/* ---- state -------------------------------------------------------------------------- */
static uint16_t table[MAX_SCAN_ROWS][4];
static uint8_t filled[(MAX_SCAN_ROWS + 7) / 8];

static uint32_t boot_id;
static uint16_t tx_seq;
static uint8_t session, have_host_version;
static uint16_t host_version;
static uint8_t state;
static uint16_t scan_id;
static uint32_t scan_rows; /* rows of the loaded table, 0: none */
static uint8_t scan_laser;
static volatile uint32_t triggers;
static uint32_t rx_errors;
static uint8_t wd_armed, wd_flag;
static uint32_t last_rx; /* low 32 bits of the board clock at the last valid host packet */

/* The last command's seq and answer, repeated for a retransmission. */
static uint8_t have_last;
static uint16_t last_seq;
static uint8_t last_type, last_len;
static uint8_t last_payload[2 + 40];

/* ---- scan timing (Timer1 compare A: trigger pin; compare B: /LDAC slot) ----------- */
static uint32_t period_ticks;
static uint64_t edge_t;        /* the current / next rising edge [ticks] */
static uint32_t ldac_t;        /* the next /LDAC slot, low 32 bits [ticks] */
static uint16_t a_epochs, b_epochs;
static uint8_t a_fall;         /* 1: compare A waits for the end of the pulse */
static uint32_t edge_index;    /* index of the next edge */
static uint32_t ldac_row;      /* next row to move to the outputs */
static volatile uint8_t scan_done;  /* the last slot passed: the laser is off */
static volatile uint8_t overruns;

#define COM1A_SET (_BV(COM1A1) | _BV(COM1A0))
#define COM1A_CLEAR _BV(COM1A1)

struct trig_event {
    uint32_t index;
    uint64_t stamp_us;
    uint16_t codes[4];
    uint8_t laser;
};
#define EVENT_Q 8u
static struct trig_event events[EVENT_Q];
static volatile uint8_t ev_head, ev_tail;

/* Matches of a compare unit before the one at `target` (each 65536 ticks apart). */
static inline uint16_t epochs_before(uint32_t target, uint32_t now)
{
    return (uint16_t)((target - now - 1u) >> 16);
}

/* Arm compare A for a rising edge at edge_t. Called with interrupts off. */
static void arm_rise(uint32_t now)
{
    a_fall = 0;
    a_epochs = epochs_before((uint32_t)edge_t, now);
    /* the output mode first, then the compare value */
    TCCR1A = (TCCR1A & ~(_BV(COM1A1) | _BV(COM1A0))) | (a_epochs ? 0 : COM1A_SET);
    OCR1A = (uint16_t)edge_t;
}

static void arm_ldac(uint32_t now)
{
    b_epochs = epochs_before(ldac_t, now);
    OCR1B = (uint16_t)ldac_t;
}

ISR(TIMER1_COMPA_vect)
{
    if (a_epochs) {
        if (--a_epochs == 0)
            TCCR1A = (TCCR1A & ~(_BV(COM1A1) | _BV(COM1A0))) | COM1A_SET;
        return;
    }
    if (!a_fall) {
        /* The pin went high at this match: record the trigger. */
        TCCR1A = (TCCR1A & ~(_BV(COM1A1) | _BV(COM1A0))) | COM1A_CLEAR;
        OCR1A = (uint16_t)(edge_t + PULSE_TICKS);
        a_fall = 1;
        uint8_t next = (ev_head + 1) & (EVENT_Q - 1);
        if (next == ev_tail) {
            overruns++;
        } else {
            struct trig_event *e = &events[ev_head];
            e->index = edge_index;
            /* the compare output changes one timer tick after TCNT1 equals OCR1A */
            e->stamp_us = ticks_to_us(edge_t + 1);
            for (uint8_t ch = 0; ch < 4; ch++)
                e->codes[ch] = out_codes[ch];
            e->laser = laser_is_on();
            ev_head = next;
        }
        edge_index++;
        triggers++;
        return;
    }
    /* End of the pulse: schedule the next edge, or stop after the last one. */
    if (edge_index >= scan_rows) {
        TCCR1A &= ~(_BV(COM1A1) | _BV(COM1A0));
        TIMSK1 &= ~_BV(OCIE1A);
        return;
    }
    uint32_t now = (uint32_t)(edge_t + PULSE_TICKS);
    edge_t += period_ticks;
    arm_rise(now);
}

ISR(TIMER1_COMPB_vect)
{
    if (b_epochs) {
        b_epochs--;
        return;
    }
    if (ldac_row >= scan_rows) {
        /* half a period after the last edge: the scan is over */
        laser_set(0);
        TIMSK1 &= ~_BV(OCIE1B);
        scan_done = 1;
        return;
    }
    dac_ldac();
    const uint16_t *row = table[ldac_row];
    for (uint8_t ch = 0; ch < 4; ch++)
        out_codes[ch] = row[ch];
    ldac_row++;
    uint32_t now = ldac_t;
    ldac_t += period_ticks;
    arm_ldac(now);
    /* The next row's SPI transfer (20 us) runs with interrupts on, so that the UART
     * receiver and the trigger compare are never held up by it. */
    sei();
    if (ldac_row < scan_rows)
        dac_load(table[ldac_row]);
}

/* Stop triggering and the /LDAC slots; the trigger pin returns to PORTB (low). */
static void timing_stop(void)
{
    uint8_t sreg = SREG;
    cli();
    TIMSK1 &= ~(_BV(OCIE1A) | _BV(OCIE1B));
    TCCR1A &= ~(_BV(COM1A1) | _BV(COM1A0));
    PORTB &= ~_BV(PIN_TRIG);
    SREG = sreg;
}

static void timing_start(uint32_t period_us)
{
    period_ticks = period_us * TICKS_PER_US;
    dac_load(table[0]);
    dac_ldac();
    for (uint8_t ch = 0; ch < 4; ch++)
        out_codes[ch] = table[0][ch];
    if (scan_rows > 1)
        dac_load(table[1]);
    laser_set(scan_laser);
    cli();
    edge_index = 0;
    ldac_row = 1;
    scan_done = 0;
    overruns = 0;
    ev_head = ev_tail = 0;
    uint32_t now = (uint32_t)now_ticks();
    edge_t = now_ticks() + period_ticks / 2;
    ldac_t = (uint32_t)edge_t + period_ticks / 2;
    arm_rise(now);
    arm_ldac(now);
    TIFR1 = _BV(OCF1A) | _BV(OCF1B);
    TIMSK1 |= _BV(OCIE1A) | _BV(OCIE1B);
    sei();
}

/* ---- interlock ---------------------------------------------------------------------- */
ISR(INT4_vect)
{
    if (interlock_open()) {
        laser_set(0);
        TIMSK1 &= ~(_BV(OCIE1A) | _BV(OCIE1B));
        TCCR1A &= ~(_BV(COM1A1) | _BV(COM1A0));
        PORTB &= ~_BV(PIN_TRIG);
    }
}

/* ---- sending -------------------------------------------------------------------------- */
static void put16(uint8_t *p, uint16_t v) { p[0] = (uint8_t)v; p[1] = (uint8_t)(v >> 8); }
static void put32(uint8_t *p, uint32_t v) { put16(p, (uint16_t)v); put16(p + 2, (uint16_t)(v >> 16)); }
static void put64(uint8_t *p, uint64_t v) { put32(p, (uint32_t)v); put32(p + 4, (uint32_t)(v >> 32)); }
static uint16_t get16(const uint8_t *p) { return (uint16_t)p[0] | ((uint16_t)p[1] << 8); }
static uint32_t get32(const uint8_t *p) { return (uint32_t)get16(p) | ((uint32_t)get16(p + 2) << 16); }

static void send(uint8_t type, const uint8_t *payload, uint8_t n)
{
    uint8_t pkt[HEADER_SIZE + 48 + CRC_SIZE];
    uint8_t enc[sizeof pkt + 2];
    pkt[0] = type;
    put16(pkt + 1, tx_seq++);
    memcpy(pkt + HEADER_SIZE, payload, n);
    put32(pkt + HEADER_SIZE + n, crc32(pkt, HEADER_SIZE + n));
    uint16_t len = cobs_encode(pkt, HEADER_SIZE + n + CRC_SIZE, enc);
    enc[len++] = 0;
    link_write(enc, len);
}

static uint8_t pack_info(uint8_t *p)
{
    put16(p, PROTOCOL_VERSION);
    memset(p + 2, 0, 16);
    memcpy(p + 2, FIRMWARE_ID, sizeof FIRMWARE_ID - 1);
    p[18] = 16;
    p[19] = 4;
    put32(p + 20, boot_id);
    put64(p + 24, ticks_to_us(now_ticks()));
    put32(p + 32, MAX_SCAN_ROWS);
    put32(p + 36, MIN_PERIOD_US);
    return 40;
}

static uint8_t pack_status(uint8_t *p)
{
    put32(p, boot_id);
    put64(p + 4, ticks_to_us(now_ticks()));
    p[12] = state;
    p[13] = (wd_flag ? FLAG_WATCHDOG : 0) | (interlock_open() ? FLAG_INTERLOCK : 0);
    p[14] = laser_is_on();
    uint8_t sreg = SREG;
    cli();
    for (uint8_t ch = 0; ch < 4; ch++)
        put16(p + 15 + 2 * ch, out_codes[ch]);
    uint32_t trig = triggers;
    SREG = sreg;
    put16(p + 23, scan_id);
    put32(p + 25, trig);
    put32(p + 29, rx_errors);
    return 33;
}

static void send_status(void)
{
    uint8_t p[33];
    send(T_STATUS, p, pack_status(p));
}

static void send_fault(uint8_t code, uint32_t detail)
{
    uint8_t p[13];
    p[0] = code;
    put64(p + 1, ticks_to_us(now_ticks()));
    put32(p + 9, detail);
    send(T_FAULT, p, 13);
}

/* Answer a command and remember the answer for a retransmission of the same seq. */
static void respond(uint16_t seq, uint8_t type, const uint8_t *data, uint8_t n)
{
    uint8_t p[2 + 40];
    put16(p, seq);
    memcpy(p + 2, data, n);
    have_last = 1;
    last_seq = seq;
    last_type = type;
    last_len = 2 + n;
    memcpy(last_payload, p, last_len);
    send(type, p, last_len);
}

static void ack(uint16_t seq) { respond(seq, T_ACK, 0, 0); }

static void nak(uint16_t seq, uint8_t reason) { respond(seq, T_NAK, &reason, 1); }

/* ---- outputs ------------------------------------------------------------------------ */
static void set_outputs(const uint16_t *codes)
{
    dac_load(codes);
    dac_ldac();
    uint8_t sreg = SREG;
    cli();
    for (uint8_t ch = 0; ch < 4; ch++)
        out_codes[ch] = codes[ch];
    SREG = sreg;
}

static void go_safe(void)
{
    static const uint16_t zero[4] = {CODE_ZERO, CODE_ZERO, CODE_ZERO, CODE_ZERO};
    laser_set(0);
    timing_stop();
    state = STATE_IDLE;
    set_outputs(zero);
}

/* ---- commands ------------------------------------------------------------------------- */
/* Payload checks of docs/board-protocol.md; 0 if the packet is malformed. */
static uint8_t codes_ok(const uint8_t *p, uint8_t n_codes)
{
    for (uint8_t i = 0; i < n_codes; i++)
        if (get16(p + 2 * i) == 0)
            return 0;
    return 1;
}

static uint8_t well_formed(uint8_t type, const uint8_t *p, uint8_t n)
{
    switch (type) {
    case T_HELLO:
        return n == 2;
    case T_HEARTBEAT:
    case T_SCAN_STOP:
    case T_SAFE:
    case T_GET_STATUS:
        return n == 0;
    case T_SET_VOLTS:
        return n == 8 && codes_ok(p, 4);
    case T_LASER:
        return n == 1 && p[0] <= 1;
    case T_SCAN_BEGIN:
        return n == 6 && get32(p + 2) != 0;
    case T_SCAN_DATA:
        return n >= 7 && p[6] >= 1 && p[6] <= ROWS_PER_CHUNK && n == 7u + 8u * p[6]
               && codes_ok(p + 7, 4 * p[6]);
    case T_SCAN_START:
        return n == 15 && get32(p + 2) != 0 && get32(p + 6) != 0 && p[10] <= 1;
    default:
        return 0;
    }
}

static uint8_t table_complete(void)
{
    for (uint32_t r = 0; r < scan_rows; r++)
        if (!(filled[r >> 3] & (1u << (r & 7))))
            return 0;
    return 1;
}

static void execute(uint16_t seq, uint8_t type, const uint8_t *p)
{
    if (type == T_SAFE) {
        go_safe();
        ack(seq);
        return;
    }
    if (type == T_GET_STATUS) {
        uint8_t st[33];
        respond(seq, T_ACK, st, pack_status(st));
        return;
    }
    if (!session) {
        nak(seq, have_host_version && host_version != PROTOCOL_VERSION ? NAK_VERSION
                                                                        : NAK_NO_SESSION);
        return;
    }
    uint8_t scanning = state == STATE_SCANNING;
    if (type == T_SCAN_STOP) {
        if (scanning || laser_is_on()) {
            timing_stop();
            laser_set(0);
            state = STATE_IDLE;
        }
        ack(seq);
        return;
    }
    if (type == T_LASER) {
        if (p[0] && scanning) {
            nak(seq, NAK_BUSY);
        } else if (p[0] && interlock_open()) {
            nak(seq, NAK_INTERLOCK);
        } else {
            laser_set(p[0]);
            ack(seq);
        }
        return;
    }
    if (scanning) {
        nak(seq, NAK_BUSY);
        return;
    }
    switch (type) {
    case T_SET_VOLTS: {
        if (interlock_open()) {
            nak(seq, NAK_INTERLOCK);
            return;
        }
        uint16_t codes[4];
        for (uint8_t ch = 0; ch < 4; ch++)
            codes[ch] = get16(p + 2 * ch);
        set_outputs(codes);
        ack(seq);
        return;
    }
    case T_SCAN_BEGIN: {
        uint32_t n = get32(p + 2);
        if (n > MAX_SCAN_ROWS) {
            nak(seq, NAK_BAD_ARGUMENT);
            return;
        }
        scan_rows = n;
        memset(filled, 0, sizeof filled);
        scan_id = get16(p);
        state = STATE_LOADED;
        triggers = 0;
        ack(seq);
        return;
    }
    case T_SCAN_DATA: {
        uint32_t off = get32(p + 2);
        uint8_t count = p[6];
        if (scan_rows == 0 || get16(p) != scan_id || off > scan_rows
            || off + count > scan_rows) {
            nak(seq, NAK_BAD_ARGUMENT);
            return;
        }
        memcpy(table[off], p + 7, 8u * count); /* the AVR is little-endian, as the wire */
        for (uint32_t r = off; r < off + count; r++)
            filled[r >> 3] |= (uint8_t)(1u << (r & 7));
        ack(seq);
        return;
    }
    case T_SCAN_START: {
        uint32_t n = get32(p + 2);
        uint32_t period = get32(p + 6);
        if (scan_rows == 0 || get16(p) != scan_id || n != scan_rows || !table_complete()
            || crc32((const uint8_t *)table, (uint16_t)(8u * scan_rows)) != get32(p + 11)) {
            nak(seq, NAK_TABLE_MISMATCH);
            return;
        }
        if (period < MIN_PERIOD_US || period > MAX_PERIOD_US) {
            nak(seq, NAK_BAD_ARGUMENT);
            return;
        }
        if (p[10] && interlock_open()) {
            nak(seq, NAK_INTERLOCK);
            return;
        }
        scan_laser = p[10];
        triggers = 0;
        state = STATE_SCANNING;
        timing_start(period);
        ack(seq);
        return;
    }
    default:
        nak(seq, NAK_BAD_MESSAGE);
    }
}

/* One complete frame (without its delimiter) from the host. */
static void handle_frame(uint8_t *buf, uint16_t n)
{
    int16_t len = cobs_decode_inplace(buf, n);
    if (len < 0 || len < (int16_t)(HEADER_SIZE + CRC_SIZE) || len > (int16_t)MAX_PACKET) {
        rx_errors++;
        return;
    }
    uint8_t plen = (uint8_t)(len - HEADER_SIZE - CRC_SIZE);
    if (crc32(buf, HEADER_SIZE + plen) != get32(buf + HEADER_SIZE + plen)) {
        rx_errors++;
        return;
    }
    uint8_t type = buf[0];
    uint16_t seq = get16(buf + 1);
    const uint8_t *p = buf + HEADER_SIZE;
    if (type >= 0x80)
        return; /* a board message sent back to the board: ignored */
    if (!well_formed(type, p, plen)) {
        rx_errors++;
        nak(seq, NAK_BAD_MESSAGE);
        return;
    }
    last_rx = (uint32_t)now_ticks();
    wd_armed = 1;
    if (type == T_HEARTBEAT) {
        send_status();
        wd_flag = 0;
        return;
    }
    if (type == T_HELLO) {
        host_version = get16(p);
        have_host_version = 1;
        session = host_version == PROTOCOL_VERSION;
        wd_flag = 0;
        uint8_t info[40];
        respond(seq, T_ACK, info, pack_info(info));
        return;
    }
    if (have_last && last_seq == seq) {
        send(last_type, last_payload, last_len); /* a retransmission: same answer again */
        return;
    }
    execute(seq, type, p);
}

/* ---- main loop -------------------------------------------------------------------------- */
static uint8_t frame[MAX_ENCODED_FRAME];
static uint16_t frame_len;
static uint8_t frame_oversize;

static void poll_rx(void)
{
    int16_t c;
    while ((c = link_getc()) >= 0) {
        if (c == 0) {
            if (frame_oversize)
                rx_errors++;
            else if (frame_len)
                handle_frame(frame, frame_len);
            frame_len = 0;
            frame_oversize = 0;
        } else if (frame_len < MAX_ENCODED_FRAME) {
            frame[frame_len++] = (uint8_t)c;
        } else {
            frame_oversize = 1;
        }
    }
}

static void send_events(void)
{
    while (ev_tail != ev_head) {
        const struct trig_event *e = &events[ev_tail];
        uint8_t p[28];
        put32(p, boot_id);
        put16(p + 4, scan_id);
        put32(p + 6, e->index);
        put64(p + 10, e->stamp_us);
        for (uint8_t ch = 0; ch < 4; ch++)
            put16(p + 18 + 2 * ch, e->codes[ch]);
        p[26] = e->laser;
        p[27] = 0; /* settled: the row reached the outputs half a period earlier */
        ev_tail = (ev_tail + 1) & (EVENT_Q - 1);
        send(T_EVENT, p, 28);
        poll_rx();
    }
}

static uint32_t next_boot_id(void)
{
    uint32_t *addr = (uint32_t *)0;
    uint32_t count = eeprom_read_dword(addr) + 1u;
    eeprom_write_dword(addr, count);
    uint32_t id = crc32((const uint8_t *)&count, 4);
    return id ? id : 1u;
}

int main(void)
{
    /* Timer1: normal mode, F_CPU / 8, overflow interrupt extends it to the board clock */
    TCCR1A = 0;
    TCCR1B = _BV(CS11);
    TIMSK1 = _BV(TOIE1);
    dac_init();
    /* interlock: input with pull-up, INT4 on any change */
    DDRE &= ~_BV(PIN_INTERLOCK);
    PORTE |= _BV(PIN_INTERLOCK);
    EICRB = (EICRB & ~(_BV(ISC41) | _BV(ISC40))) | _BV(ISC40);
    EIFR = _BV(INTF4);
    EIMSK |= _BV(INT4);
    boot_id = next_boot_id();
    link_init();
    sei();
    {
        uint8_t info[40];
        send(T_BOOT, info, pack_info(info));
    }
    uint8_t interlock_reported = 0;
    set_sleep_mode(SLEEP_MODE_IDLE);
    for (;;) {
        poll_rx();
        send_events();
        if (overruns) {
            uint8_t lost = overruns;
            overruns = 0;
            send_fault(FAULT_OVERRUN, lost);
        }
        if (scan_done && ev_tail == ev_head) {
            scan_done = 0;
            if (state == STATE_SCANNING) {
                state = STATE_DONE;
                send_status();
            }
        }
        if (interlock_open()) {
            if (!interlock_reported) {
                /* the interrupt switched the laser off; the galvos are parked here */
                go_safe();
                interlock_reported = 1;
                send_fault(FAULT_INTERLOCK, 0);
                send_status();
            }
        } else {
            interlock_reported = 0;
        }
        if (wd_armed && (uint32_t)now_ticks() - last_rx > WATCHDOG_TICKS) {
            wd_armed = 0;
            wd_flag = 1;
            go_safe();
            send_fault(FAULT_WATCHDOG, 0);
            send_status();
        }
        /* Idle until the next interrupt (a received byte, a trigger, the interlock, or the
         * clock's overflow every 32.8 ms, which bounds the watchdog check's delay). */
        cli();
        if (!link_rx_pending() && ev_tail == ev_head && !scan_done && !overruns) {
            sleep_enable();
            sei();
            sleep_cpu();
            sleep_disable();
        }
        sei();
    }
}
