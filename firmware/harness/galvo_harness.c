/*
 * galvo_harness: the galvo board firmware in simavr, with the board around it.
 *
 *   galvo_harness [options] build/galvo_board.elf
 *     --log FILE        cycle-stamped log of everything the board did (below)
 *     --pty             serve the firmware's UART0 on a new pty; its path is the first line
 *                       on stdout. Commands on stdin, one per line:
 *                         interlock open | interlock closed | reset | reset-after-event N |
 *                         hold-reset MS (reset, then hold the MCU in reset for MS wall-clock
 *                         milliseconds, as a bootloader keeps the firmware from starting) |
 *                         unplug | replug | sync (flush the log, answer "sync <cycle>") |
 *                         quit
 *     --realtime        lock simulated time to the wall clock (16 Mcycles per second), as a
 *                       host with its own timers (heartbeat, ACK timeouts) needs
 *     --rate R          with --realtime: simulated seconds per wall-clock second (default 1)
 *     --max-lag MS      with --realtime: when the simulation falls more than MS wall-clock
 *                       milliseconds behind (the machine stalled the harness), slip the
 *                       wall clock instead of catching up in a burst: a burst would hand
 *                       the firmware the host's bytes of the whole stall at once and then
 *                       run the board's watchdog out in fast-forward. Logged as "slip <us>".
 *                       Default 0: always catch up.
 *     --script FILE     scripted host, in simulated time: lines "<t_us> tx <hex bytes>",
 *                       "<t_us> interlock open|closed", "<t_us> reset", "<t_us> end"
 *     --seconds S       stop after S simulated seconds
 *     --boot-count N    the EEPROM boot counter before power-up (so each run has its own
 *                       boot id)
 *     --edge-udp PORT   at each rising edge of the camera trigger, one UDP datagram to
 *                       127.0.0.1:PORT (a camera's trigger input, e.g. the fake GigE Vision
 *                       camera's Line0), carrying what the rig's physics needs at that
 *                       instant (below)
 *
 * Models:
 *   - AD5754R on the SPI: 24-bit words framed by /SYNC (PL0); output range, power control
 *     and DAC registers; /LDAC (PL1) falling edge copies all input registers to the
 *     outputs, as does a write while /LDAC is held low.
 *   - SPI bytes take 8 SPI clocks at the rate SPCR/SPSR select (simavr 1.6 clocks every
 *     byte in a fixed 100 us; this harness installs its own SPDR write handler).
 *   - camera trigger PB5 (OC1A, driven as the chip drives it: see set_trig), laser enable
 *     PA0 (pulled down), interlock PE4 (a switch to GND: closed drives it low, open lets
 *     the pull-up win).
 *
 * Edge datagram (--edge-udp), 32 bytes, little-endian:
 *   u64 the edge's instant [ns]: in --realtime mode CLOCK_REALTIME at power-up plus the
 *       board's crystal time of the edge (so a late datagram still carries its edge's time,
 *       as a camera latches its timestamp at the edge; the harness's slips and --rate do not
 *       move it), otherwise CLOCK_REALTIME when the edge is simulated;
 *   u16 x 4 the AD5754R output codes at the edge (VOUTA..VOUTD);
 *   u8 powered channels (bit mask), u8 output range code of channel A (4: +-10 V),
 *   u8 laser enable level at the edge, 5 bytes 0;
 *   u64 the edge's CPU cycle.
 *   The trigger line carries only the edge; the DAC outputs are the galvos' drive voltages,
 *   which a simulated rig needs to place its mirrors (the physics, not a message a board
 *   sends).
 *
 * Log lines ("<cycle> <what> ..."), cycle = AVR clock cycles at 16 MHz since power-up:
 *   boot | dac <24-bit word hex> | out <c0> <c1> <c2> <c3> <powered mask> <range code> |
 *   trig 0|1 | laser 0|1 | interlock open|closed | rx <hex> | tx <hex frame> | end
 */
#define _GNU_SOURCE
#include <arpa/inet.h>
#include <errno.h>
#include <stdarg.h>
#include <fcntl.h>
#include <stdint.h>
#include <stdio.h>
#include <stdlib.h>
#include <string.h>
#include <termios.h>
#include <time.h>
#include <netinet/in.h>
#include <sys/socket.h>
#include <unistd.h>

#include "avr_eeprom.h"
#include "avr_extint.h"
#include "avr_ioport.h"
#include "avr_uart.h"
#include "sim_avr.h"
#include "sim_elf.h"

#define SPCR_ADDR 0x4C
#define SPSR_ADDR 0x4D
#define SPDR_ADDR 0x4E
#define SPIF_BIT 7

static avr_t *avr;
static FILE *logf;
static int pty_master = -1, pty_slave = -1;
static int unplugged;
static int realtime;
static double rate = 1.0;

/* ---- log ------------------------------------------------------------------------------ */
static void logline(const char *fmt, ...) __attribute__((format(printf, 1, 2)));
static void logline(const char *fmt, ...)
{
    if (!logf)
        return;
    va_list ap;
    fprintf(logf, "%llu ", (unsigned long long)avr->cycle);
    va_start(ap, fmt);
    vfprintf(logf, fmt, ap);
    va_end(ap);
    fputc('\n', logf);
}

static void loghex(const char *what, const uint8_t *b, size_t n)
{
    if (!logf)
        return;
    fprintf(logf, "%llu %s ", (unsigned long long)avr->cycle, what);
    for (size_t i = 0; i < n; i++)
        fprintf(logf, "%02x", b[i]);
    fputc('\n', logf);
}

/* ---- AD5754R ---------------------------------------------------------------------------- */
static struct {
    int sync, ldac;     /* pin levels */
    uint32_t shift;
    int nbits;
    uint16_t input[4], dac[4];
    uint8_t range[4];   /* output range code (4 = +-10 V) */
    uint8_t power;      /* bit per powered-up channel */
} dac = {.sync = 1, .ldac = 1};

static void dac_log_out(void)
{
    logline("out %u %u %u %u %u %u", dac.dac[0], dac.dac[1], dac.dac[2], dac.dac[3],
            dac.power, dac.range[0]);
}

static void dac_update_outputs(void)
{
    memcpy(dac.dac, dac.input, sizeof dac.dac);
    dac_log_out();
}

static void dac_execute(uint32_t w)
{
    logline("dac %06x", w);
    if (w & 0x800000)
        return; /* readback: not modelled (the firmware does not read back) */
    unsigned reg = (w >> 19) & 7, addr = (w >> 16) & 7;
    uint16_t data = w & 0xFFFF;
    switch (reg) {
    case 0: /* DAC register */
        if (addr == 4) {
            for (int c = 0; c < 4; c++)
                dac.input[c] = data;
        } else if (addr < 4) {
            dac.input[addr] = data;
        }
        if (!dac.ldac)
            dac_update_outputs();
        break;
    case 1: /* output range select */
        for (int c = 0; c < 4; c++)
            if (addr == 4 || addr == (unsigned)c)
                dac.range[c] = data & 7;
        break;
    case 2: /* power control */
        if (addr == 0) {
            dac.power = data & 0x0F;
            dac_log_out();
        }
        break;
    case 3: /* control: load (addr 5) = /LDAC */
        if (addr == 5)
            dac_update_outputs();
        break;
    }
}

static void sync_hook(struct avr_irq_t *irq, uint32_t value, void *param)
{
    (void)irq; (void)param;
    value = value ? 1 : 0;
    if ((int)value == dac.sync)
        return;
    dac.sync = value;
    if (!value) {
        dac.shift = 0;
        dac.nbits = 0;
    } else if (dac.nbits == 24) {
        dac_execute(dac.shift & 0xFFFFFF);
    } else if (dac.nbits) {
        logline("dac-frame-error %d", dac.nbits);
    }
}

static void ldac_hook(struct avr_irq_t *irq, uint32_t value, void *param)
{
    (void)irq; (void)param;
    value = value ? 1 : 0;
    if ((int)value == dac.ldac)
        return;
    dac.ldac = value;
    if (!value)
        dac_update_outputs();
}

static void spi_byte_to_dac(uint8_t b)
{
    if (dac.sync)
        return; /* not selected */
    dac.shift = (dac.shift << 8) | b;
    dac.nbits += 8;
}

/* SPDR writes: the byte takes 8 SPI clocks, then SPIF rises. */
static uint8_t spi_pending;

static avr_cycle_count_t spi_done(struct avr_t *a, avr_cycle_count_t when, void *param)
{
    (void)param; (void)when;
    spi_byte_to_dac(spi_pending);
    a->data[SPSR_ADDR] |= 1 << SPIF_BIT;
    return 0;
}

static void spdr_write(struct avr_t *a, avr_io_addr_t addr, uint8_t v, void *param)
{
    (void)param;
    a->data[addr] = v;
    a->data[SPSR_ADDR] &= ~(1 << SPIF_BIT);
    uint8_t spcr = a->data[SPCR_ADDR], spsr = a->data[SPSR_ADDR];
    if (!(spcr & 0x40) || !(spcr & 0x10))
        return; /* SPI off, or a slave */
    static const uint8_t div[4] = {4, 16, 64, 128};
    uint32_t d = div[spcr & 3];
    if (spsr & 1)
        d /= 2;
    spi_pending = v;
    avr_cycle_timer_register(a, 8 * d, spi_done, NULL);
}

/* ---- pins ------------------------------------------------------------------------------- */
static int trig_level, laser_level;
static long long reset_after_event = -1;
static int reset_requested;

/* ---- the trigger wire to a camera (--edge-udp) ------------------------------------------ */
static int edge_sock = -1;
static struct sockaddr_in edge_addr;
static double wall0;          /* CLOCK_MONOTONIC [s] of cycle 0 (moved by a held reset, a slip) */
static double edge0;          /* CLOCK_MONOTONIC [s] of cycle 0 for the edges' instants */
static double max_lag;        /* [s], 0: catch up */
static double mono_to_real;   /* CLOCK_REALTIME - CLOCK_MONOTONIC [s] */

static void put_le(uint8_t *b, uint64_t v, int n)
{
    for (int i = 0; i < n; i++)
        b[i] = (uint8_t)(v >> (8 * i));
}

static void send_edge(void)
{
    if (edge_sock < 0)
        return;
    uint8_t b[32] = {0};
    /* the edges' instants follow the board's crystal from power-up (16 MHz, whatever --rate
     * and the harness's slips): a camera clock of its own, which the host pairs against the
     * board's clock */
    double t = realtime ? edge0 + avr->cycle / 16e6 : 0.0;
    uint64_t ns;
    if (realtime) {
        ns = (uint64_t)((long double)(t + mono_to_real) * 1e9L);
    } else {
        struct timespec ts;
        clock_gettime(CLOCK_REALTIME, &ts);
        ns = (uint64_t)ts.tv_sec * 1000000000ull + (uint64_t)ts.tv_nsec;
    }
    put_le(b, ns, 8);
    for (int c = 0; c < 4; c++)
        put_le(b + 8 + 2 * c, dac.dac[c], 2);
    b[16] = dac.power;
    b[17] = dac.range[0];
    b[18] = (uint8_t)laser_level;
    put_le(b + 24, avr->cycle, 8);
    /* a camera that is not listening loses the edge, as on a wire to a dead camera */
    (void)sendto(edge_sock, b, sizeof b, MSG_DONTWAIT, (struct sockaddr *)&edge_addr,
                 sizeof edge_addr);
}

static void set_trig(int level)
{
    if (level == trig_level)
        return;
    trig_level = level;
    logline("trig %d", level);
    if (level)
        send_edge();
}

/* The trigger pin OC1A as the ATmega2560 drives it: while COM1A selects an output mode, the
 * compare unit alone sets the pin, at each compare match; otherwise PORTB5 does. simavr 1.6
 * also applies its PWM-mode "set/clear at overflow" to normal mode (and on every OCR1A
 * write), so the pin's own IRQ is only believed while COM1A is disconnected, and the
 * compare matches are taken from the compare interrupt's flag. */
#define TCCR1A_ADDR 0x80
static int com1a(void) { return (avr->data[TCCR1A_ADDR] >> 6) & 3; }

static void trig_pin_hook(struct avr_irq_t *irq, uint32_t value, void *param)
{
    (void)irq; (void)param;
    if (com1a() == 0)
        set_trig(value ? 1 : 0);
}

static void compa_hook(struct avr_irq_t *irq, uint32_t value, void *param)
{
    (void)irq; (void)param;
    if (!value)
        return;
    switch (com1a()) {
    case 1: set_trig(!trig_level); break;
    case 2: set_trig(0); break;
    case 3: set_trig(1); break;
    default: break;
    }
}

static void laser_hook(struct avr_irq_t *irq, uint32_t value, void *param)
{
    (void)irq; (void)param;
    value = value ? 1 : 0;
    if ((int)value == laser_level)
        return;
    laser_level = value;
    logline("laser %u", value);
}

static avr_irq_t *interlock_irq;
static int interlock_is_open;

static void set_interlock(int open)
{
    interlock_is_open = open;
    logline("interlock %s", open ? "open" : "closed");
    /* a closed switch holds the pin low against the pull-up; open, the pull-up wins */
    avr_ioport_external_t ext = {.name = 'E', .mask = 1 << 4, .value = open ? 1 << 4 : 0};
    avr_ioctl(avr, AVR_IOCTL_IOPORT_SET_EXTERNAL('E'), &ext);
    avr_raise_irq(interlock_irq, open ? 1 : 0);
}

/* ---- UART ------------------------------------------------------------------------------- */
static uint8_t to_avr[1 << 16];
static size_t to_avr_head, to_avr_tail;
static int uart_xon;
static uint8_t tx_frame[512];
static size_t tx_len;
static uint8_t to_host[1 << 16];
static size_t to_host_len;

/* The UART's XOFF line: 1 while its receive FIFO is full or the receiver is off. Its level
 * is read before each feed (its XON notifications are not a reliable edge to wait for). */
static avr_irq_t *uart_xoff;

/* The index of an EVENT frame (COBS-decoded), or -1. */
static long long event_index(const uint8_t *f, size_t n)
{
    uint8_t pkt[512];
    size_t i = 0, w = 0;
    while (i < n) {
        uint8_t code = f[i];
        if (!code || i + code > n)
            return -1;
        memcpy(pkt + w, f + i + 1, code - 1);
        w += code - 1;
        i += code;
        if (code != 0xFF && i < n)
            pkt[w++] = 0;
    }
    if (w != 3 + 28 + 4 || pkt[0] != 0x82)
        return -1;
    return (long long)pkt[9] | (long long)pkt[10] << 8 | (long long)pkt[11] << 16
           | (long long)pkt[12] << 24;
}

static void uart_out_hook(struct avr_irq_t *irq, uint32_t value, void *param)
{
    (void)irq; (void)param;
    uint8_t b = value;
    if (tx_len < sizeof tx_frame)
        tx_frame[tx_len++] = b;
    if (!unplugged && to_host_len < sizeof to_host)
        to_host[to_host_len++] = b;
    if (b == 0) {
        loghex("tx", tx_frame, tx_len);
        long long idx = event_index(tx_frame, tx_len - 1);
        if (reset_after_event >= 0 && idx == reset_after_event) {
            reset_after_event = -1;
            reset_requested = 1;
        }
        tx_len = 0;
    }
}

static void feed_uart(avr_irq_t *uart_in)
{
    size_t start = to_avr_tail;
    uart_xon = avr_regbit_get(avr, (avr_regbit_t)AVR_IO_REGBIT(0xC1, 4)) /* RXEN0 */
               && !uart_xoff->value;
    while (uart_xon && to_avr_tail != to_avr_head) {
        avr_raise_irq(uart_in, to_avr[to_avr_tail]);
        to_avr_tail = (to_avr_tail + 1) & (sizeof to_avr - 1);
        uart_xon = !uart_xoff->value;
    }
    if (logf && to_avr_tail != start) {
        fprintf(logf, "%llu rx ", (unsigned long long)avr->cycle);
        for (size_t i = start; i != to_avr_tail; i = (i + 1) & (sizeof to_avr - 1))
            fprintf(logf, "%02x", to_avr[i]);
        fputc('\n', logf);
    }
}

static void queue_to_avr(const uint8_t *b, size_t n)
{
    for (size_t i = 0; i < n; i++) {
        size_t next = (to_avr_head + 1) & (sizeof to_avr - 1);
        if (next == to_avr_tail)
            return;
        to_avr[to_avr_head] = b[i];
        to_avr_head = next;
    }
}

/* ---- pty ---------------------------------------------------------------------------------- */
static void pty_open(void)
{
    pty_master = posix_openpt(O_RDWR | O_NOCTTY);
    if (pty_master < 0 || grantpt(pty_master) || unlockpt(pty_master)) {
        perror("pty");
        exit(2);
    }
    const char *name = ptsname(pty_master);
    /* keep the slave open, so that the master never reads EIO while no host has the port */
    pty_slave = open(name, O_RDWR | O_NOCTTY);
    struct termios t;
    tcgetattr(pty_slave, &t);
    cfmakeraw(&t);
    tcsetattr(pty_slave, TCSANOW, &t);
    fcntl(pty_master, F_SETFL, fcntl(pty_master, F_GETFL) | O_NONBLOCK);
    printf("pty %s\n", name);
    fflush(stdout);
}

static void pty_poll(void)
{
    uint8_t buf[4096];
    ssize_t n = read(pty_master, buf, sizeof buf);
    if (n > 0 && !unplugged)
        queue_to_avr(buf, (size_t)n);
    if (to_host_len) {
        ssize_t w = write(pty_master, to_host, to_host_len);
        if (w > 0) {
            memmove(to_host, to_host + w, to_host_len - (size_t)w);
            to_host_len -= (size_t)w;
        }
    }
}

/* A sleeping core jumps to its next cycle timer (up to Timer1's overflow, 32.8 ms away);
 * this timer bounds each jump to one I/O poll interval, so host bytes and pin changes reach
 * the firmware on time. */
#define POLL_CYCLES 800u /* 50 us */
static avr_cycle_count_t poll_tick(avr_t *a, avr_cycle_count_t when, void *param)
{
    (void)a; (void)param;
    return when + POLL_CYCLES;
}

/* ---- commands and script ----------------------------------------------------------------- */
static int quit;
static double hold_until; /* wall-clock time until which the MCU is held in reset */
static double wall_now(void);

static void board_reset(void)
{
    logline("reset");
    avr_reset(avr);
    avr_cycle_timer_register(avr, POLL_CYCLES, poll_tick, NULL); /* reset cleared it */
    /* the board's pull-ups / pull-downs hold the lines while the pins float */
    dac.sync = 1;
    dac.ldac = 1;
    if (trig_level) {
        trig_level = 0;
        logline("trig 0");
    }
    if (laser_level) {
        laser_level = 0;
        logline("laser 0");
    }
    avr_raise_irq(interlock_irq, interlock_is_open ? 1 : 0);
    uart_xon = 0;
    tx_len = 0;
    logline("boot");
}

static void command(const char *line)
{
    long long n;
    if (!strncmp(line, "interlock open", 14))
        set_interlock(1);
    else if (!strncmp(line, "interlock closed", 16))
        set_interlock(0);
    else if (sscanf(line, "hold-reset %lld", &n) == 1) {
        logline("hold-reset %lld", n);
        board_reset();
        hold_until = wall_now() + n * 1e-3;
    } else if (sscanf(line, "reset-after-event %lld", &n) == 1)
        reset_after_event = n;
    else if (!strncmp(line, "reset", 5))
        reset_requested = 1;
    else if (!strncmp(line, "unplug", 6)) {
        unplugged = 1;
        to_host_len = 0;
        logline("unplug");
    } else if (!strncmp(line, "replug", 6)) {
        unplugged = 0;
        logline("replug");
    } else if (!strncmp(line, "sync", 4)) {
        /* everything so far is in the log file: answer on stdout */
        if (logf)
            fflush(logf);
        printf("sync %llu\n", (unsigned long long)avr->cycle);
        fflush(stdout);
    } else if (!strncmp(line, "quit", 4))
        quit = 1;
}

static char stdin_buf[1024];
static size_t stdin_len;

static void stdin_poll(void)
{
    ssize_t n = read(0, stdin_buf + stdin_len, sizeof stdin_buf - 1 - stdin_len);
    if (n == 0) {
        quit = 1; /* the controlling process went away */
        return;
    }
    if (n < 0)
        return;
    stdin_len += (size_t)n;
    char *nl;
    while ((nl = memchr(stdin_buf, '\n', stdin_len))) {
        *nl = 0;
        command(stdin_buf);
        size_t used = (size_t)(nl - stdin_buf) + 1;
        memmove(stdin_buf, stdin_buf + used, stdin_len - used);
        stdin_len -= used;
    }
}

static FILE *script;
static unsigned long long script_cycle = ~0ull;
static char script_line[4096];

static void script_next(void)
{
    for (;;) {
        if (!fgets(script_line, sizeof script_line, script)) {
            script_cycle = ~0ull;
            return;
        }
        double t_us;
        int off = 0;
        if (sscanf(script_line, "%lf %n", &t_us, &off) == 1) {
            script_cycle = (unsigned long long)(t_us * 16.0 + 0.5);
            memmove(script_line, script_line + off, strlen(script_line + off) + 1);
            return;
        }
    }
}

static void script_run(void)
{
    while (avr->cycle >= script_cycle) {
        char *s = script_line;
        if (!strncmp(s, "tx ", 3)) {
            uint8_t buf[2048];
            size_t n = 0;
            for (char *h = s + 3; h[0] && h[1] && n < sizeof buf; h += 2) {
                unsigned v;
                if (sscanf(h, "%2x", &v) != 1)
                    break;
                buf[n++] = (uint8_t)v;
            }
            queue_to_avr(buf, n);
        } else if (!strncmp(s, "end", 3)) {
            quit = 1;
        } else {
            command(s);
        }
        script_next();
    }
}

/* ---- main ------------------------------------------------------------------------------------ */
static void no_sleep(avr_t *a, avr_cycle_count_t how_long) { (void)a; (void)how_long; }


static double wall_now(void)
{
    struct timespec ts;
    clock_gettime(CLOCK_MONOTONIC, &ts);
    return ts.tv_sec + ts.tv_nsec * 1e-9;
}

static avr_irq_t *pin_irq(char port, int pin)
{
    return avr_io_getirq(avr, AVR_IOCTL_IOPORT_GETIRQ(port), pin);
}

int main(int argc, char **argv)
{
    const char *elf = NULL, *log_path = NULL, *script_path = NULL;
    int use_pty = 0;
    double seconds = -1;
    long boot_count = -1;
    int edge_port = 0;
    for (int i = 1; i < argc; i++) {
        if (!strcmp(argv[i], "--log") && i + 1 < argc)
            log_path = argv[++i];
        else if (!strcmp(argv[i], "--pty"))
            use_pty = 1;
        else if (!strcmp(argv[i], "--realtime"))
            realtime = 1;
        else if (!strcmp(argv[i], "--rate") && i + 1 < argc)
            rate = atof(argv[++i]);
        else if (!strcmp(argv[i], "--max-lag") && i + 1 < argc)
            max_lag = atof(argv[++i]) * 1e-3;
        else if (!strcmp(argv[i], "--script") && i + 1 < argc)
            script_path = argv[++i];
        else if (!strcmp(argv[i], "--seconds") && i + 1 < argc)
            seconds = atof(argv[++i]);
        else if (!strcmp(argv[i], "--boot-count") && i + 1 < argc)
            boot_count = atol(argv[++i]);
        else if (!strcmp(argv[i], "--edge-udp") && i + 1 < argc)
            edge_port = atoi(argv[++i]);
        else if (argv[i][0] != '-')
            elf = argv[i];
        else {
            fprintf(stderr, "galvo_harness: unknown option %s\n", argv[i]);
            return 2;
        }
    }
    if (edge_port < 0 || edge_port > 65535) {
        fprintf(stderr, "galvo_harness: --edge-udp: port %d outside 1..65535\n", edge_port);
        return 2;
    }
    if (edge_port) {
        edge_sock = socket(AF_INET, SOCK_DGRAM, 0);
        if (edge_sock < 0) {
            perror("socket");
            return 2;
        }
        memset(&edge_addr, 0, sizeof edge_addr);
        edge_addr.sin_family = AF_INET;
        edge_addr.sin_port = htons((uint16_t)edge_port);
        edge_addr.sin_addr.s_addr = htonl(INADDR_LOOPBACK);
        struct timespec rt, mo;
        clock_gettime(CLOCK_REALTIME, &rt);
        clock_gettime(CLOCK_MONOTONIC, &mo);
        mono_to_real = (rt.tv_sec - mo.tv_sec) + (rt.tv_nsec - mo.tv_nsec) * 1e-9;
    }
    if (!elf || !(rate > 0)) {
        fprintf(stderr, "usage: galvo_harness [--log F] [--pty] [--realtime] [--script F] "
                        "[--max-lag MS] [--seconds S] [--boot-count N] [--edge-udp PORT] firmware.elf\n");
        return 2;
    }
    elf_firmware_t fw;
    memset(&fw, 0, sizeof fw);
    if (elf_read_firmware(elf, &fw)) {
        fprintf(stderr, "galvo_harness: cannot read %s\n", elf);
        return 2;
    }
    strcpy(fw.mmcu, "atmega2560");
    fw.frequency = 16000000;
    avr = avr_make_mcu_by_name(fw.mmcu);
    if (!avr) {
        fprintf(stderr, "galvo_harness: simavr has no atmega2560\n");
        return 2;
    }
    avr_init(avr);
    avr->log = LOG_ERROR;
    avr_load_firmware(avr, &fw);
    avr->sleep = no_sleep;
    if (boot_count >= 0) {
        avr_eeprom_desc_t ee;
        uint8_t v[4] = {(uint8_t)boot_count, (uint8_t)(boot_count >> 8),
                        (uint8_t)(boot_count >> 16), (uint8_t)(boot_count >> 24)};
        ee.ee = v;
        ee.offset = 0;
        ee.size = 4;
        avr_ioctl(avr, AVR_IOCTL_EEPROM_SET, &ee);
    }
    if (log_path) {
        logf = fopen(log_path, "w");
        if (!logf) {
            perror(log_path);
            return 2;
        }
        setvbuf(logf, NULL, _IOFBF, 1 << 16);
        fprintf(logf, "# galvo_harness f_cpu 16000000\n");
    }

    /* SPI: replace simavr 1.6's fixed 100 us per byte */
    avr->io[AVR_DATA_TO_IO(SPDR_ADDR)].w.c = spdr_write;
    avr->io[AVR_DATA_TO_IO(SPDR_ADDR)].w.param = NULL;

    avr_irq_register_notify(pin_irq('L', 0), sync_hook, NULL);
    avr_irq_register_notify(pin_irq('L', 1), ldac_hook, NULL);
    avr_irq_register_notify(pin_irq('B', 5), trig_pin_hook, NULL);
    avr_irq_register_notify(avr_get_interrupt_irq(avr, 17 /* TIMER1_COMPA */) + AVR_INT_IRQ_PENDING,
                            compa_hook, NULL);
    avr_irq_register_notify(pin_irq('A', 0), laser_hook, NULL);
    interlock_irq = pin_irq('E', 4);
    /* simavr polls a low INT pin every cycle while its "strict level trigger" is on, even
     * after the firmware chose edge triggering: off (INT4 is an any-change interrupt). */
    avr_extint_set_strict_lvl_trig(avr, 4, 0);

    uint32_t flags = 0;
    avr_ioctl(avr, AVR_IOCTL_UART_GET_FLAGS('0'), &flags);
    flags &= ~(AVR_UART_FLAG_STDIO | AVR_UART_FLAG_POLL_SLEEP);
    avr_ioctl(avr, AVR_IOCTL_UART_SET_FLAGS('0'), &flags);
    avr_irq_t *uart_in = avr_io_getirq(avr, AVR_IOCTL_UART_GETIRQ('0'), UART_IRQ_INPUT);
    avr_irq_register_notify(avr_io_getirq(avr, AVR_IOCTL_UART_GETIRQ('0'), UART_IRQ_OUTPUT),
                            uart_out_hook, NULL);
    uart_xoff = avr_io_getirq(avr, AVR_IOCTL_UART_GETIRQ('0'), UART_IRQ_OUT_XOFF);

    if (use_pty) {
        pty_open();
        fcntl(0, F_SETFL, fcntl(0, F_GETFL) | O_NONBLOCK);
    }
    if (script_path) {
        script = fopen(script_path, "r");
        if (!script) {
            perror(script_path);
            return 2;
        }
        script_next();
    }
    logline("boot");
    set_interlock(0);

    unsigned long long stop_cycle = seconds >= 0 ? (unsigned long long)(seconds * 16e6) : ~0ull;
    const unsigned chunk = POLL_CYCLES;
    avr_cycle_timer_register(avr, POLL_CYCLES, poll_tick, NULL);
    wall0 = edge0 = wall_now();
    double last_flush = wall0;
    while (!quit && avr->cycle < stop_cycle) {
        if (hold_until > 0) {
            /* held in reset: nothing runs; the host's bytes are lost, as a bootloader
             * waiting for a programmer would not pass them on */
            if (wall_now() < hold_until) {
                struct timespec ts = {0, 1000000};
                nanosleep(&ts, NULL);
                if (use_pty) {
                    pty_poll();
                    stdin_poll();
                }
                to_avr_tail = to_avr_head;
                continue;
            }
            hold_until = 0;
            wall0 = wall_now() - avr->cycle / 16e6 / rate;
        }
        unsigned long long target = avr->cycle + chunk;
        while (avr->cycle < target) {
            int st = avr_run(avr);
            if (st == cpu_Done || st == cpu_Crashed) {
                logline("crashed %d", st);
                quit = 1;
                break;
            }
        }
        if (script)
            script_run();
        if (use_pty) {
            pty_poll();
            stdin_poll();
        }
        if (reset_requested) {
            reset_requested = 0;
            board_reset();
        }
        feed_uart(uart_in);
        if (realtime) {
            double ahead = avr->cycle / 16e6 / rate - (wall_now() - wall0);
            if (max_lag > 0 && -ahead > max_lag) {
                logline("slip %.0f", -ahead * 1e6);
                wall0 -= ahead; /* from now on, simulated time follows the wall clock again */
                ahead = 0;
            }
            if (ahead > 0.0005) {
                struct timespec ts = {0, (long)(ahead * 1e9)};
                nanosleep(&ts, NULL);
            }
        }
        if (logf && use_pty) {
            double now = wall_now();
            if (now - last_flush > 0.02) {
                fflush(logf);
                last_flush = now;
            }
        }
    }
    logline("end");
    if (logf)
        fclose(logf);
    return 0;
}
