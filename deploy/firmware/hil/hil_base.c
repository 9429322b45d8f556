/*
 * hil_base: the motor base's compiled firmware on a simulated ATmega2560 (simavr, 16 MHz), with
 * its serial port on a pseudo-terminal and two simulated DC motors with quadrature encoders.
 *
 *   hil_base FIRMWARE.elf --link PATH [options]
 *
 * The firmware's USART0 (the Mega's USB serial port, the one the Pi talks to) is bridged to a
 * pseudo-terminal; PATH is a symlink to it, for the agent's driver to open as it would open
 * /dev/mrslam-base. The harness reads the pins the firmware drives (PWM on PE3/OC3A and
 * PH3/OC4A, directions on PA0..PA3) and moves each motor by a first-order model: the motor's
 * speed approaches max_speed * effective duty with time constant tau, where the effective
 * duty is 0 below the dead band and scales linearly above it, signed by the direction pins
 * (IN1 high = positive, IN2 high = negative, both equal = no drive). Each motor turns an
 * encoder whose A and B channels it sets on PE4/PG5 (left) and PE5/PH4 (right), A leading B
 * for positive rotation; one tick is one edge of A.
 *
 * The bridge runs in the simulation's own thread and hands the host's bytes to the UART at the
 * wire's rate (one per 87 us); simavr 1.6's uart_pty part is not used because its thread feeds
 * the UART without synchronising with the simulation.
 *
 * Options:
 *   --link PATH          symlink to the pseudo-terminal (required)
 *   --speed F            simulated time runs at most F times wall time (default 1; 0: no limit)
 *   --max-speed L,R      wheel ticks/s at full duty (default 2100,1800)
 *   --tau S              motor time constant [s] (default 0.1)
 *   --dead-band D        duty that only overcomes friction (default 0.05)
 *   --mount L,R          wheel forward = mount * motor rotation (default 1,-1: right mirrored)
 *   --sample-ms MS       period of the M lines (default 5)
 *   --set SYMBOL=VALUE   write a 32-bit value into a firmware variable when main() starts
 *                        (e.g. boardMs, leftTicks: counters near their wrap point)
 *
 * Output on stdout, one line each, times in simulated microseconds:
 *   I <text>                          information (I ready <link> once the pty is up)
 *   RX <t_first> <t_last> <hex>       a frame delivered to the board's UART (from 0xAA 0x55)
 *   TX <t_first> <t_last> <hex>       a frame the board's UART sent
 *   P <t> <pin> <0|1>                 a direction pin changed (L_IN1 L_IN2 R_IN1 R_IN2)
 *   M <t> <dl> <dr> <vl> <vr> <nl> <nr>
 *                                     every sample: mean drive over the sample in the wheel's
 *                                     forward sense [-1, 1], wheel speeds [ticks/s] and the
 *                                     true wheel ticks (the encoder edges made, signed)
 * Commands on stdin, one a line:
 *   unplug | plug | plug reset        the USB cable out / in (reset: the board restarts)
 *   mute | unmute                     drop / pass the bytes from the host
 *   corrupt-rx | corrupt-tx           flip a bit in the next frame to / from the board
 *   quit                              (end of stdin too)
 */
#define _GNU_SOURCE
#include <errno.h>
#include <fcntl.h>
#include <math.h>
#include <poll.h>
#include <pty.h>
#include <stdarg.h>
#include <stdio.h>
#include <stdlib.h>
#include <string.h>
#include <termios.h>
#include <time.h>
#include <unistd.h>

#include "avr_ioport.h"
#include "avr_uart.h"
#include "sim_avr.h"
#include "sim_elf.h"
#include "sim_time.h"

#define STEP_US 50        /* motor model and encoder step */
#define SERVICE_US 50     /* pty, stdin and pacing */
#define BYTE_US 86.8      /* one byte, 10 bits at 115200 baud: the host's bytes arrive no faster */

static avr_t *avr;
static double speed_factor = 1.0;
static double tau = 0.1, dead_band = 0.05;
static unsigned sample_us = 5000;

/* --- output -------------------------------------------------------------------------------- */
/* simulated time goes on across a reset of the board (which restarts simavr's cycle count) */
static avr_cycle_count_t cycle_base;
static unsigned long long now_us(void) { return avr_cycles_to_usec(avr, cycle_base + avr->cycle); }

static void out(const char *fmt, ...) {
	va_list ap;
	va_start(ap, fmt);
	vprintf(fmt, ap);
	va_end(ap);
	fflush(stdout);
}

static void quiet_logger(struct avr_t *a, const int level, const char *fmt, va_list ap) {
	(void)a;
	if (level <= LOG_WARNING) vfprintf(stderr, fmt, ap);
}

/* --- motors -------------------------------------------------------------------------------- */
typedef struct {
	const char *name;
	char pwm_port;
	int pwm_bit, in1_bit, in2_bit;          /* direction pins on port A */
	char a_port, b_port;
	int a_bit, b_bit;
	avr_irq_t *enc_a, *enc_b;
	double max_speed;                       /* wheel ticks/s at full duty */
	int mount;
	/* pins */
	int pwm, in1, in2;
	avr_cycle_count_t pwm_since, high_cycles;
	/* model, in the motor's own sense */
	double speed, pos;                      /* ticks/s, ticks */
	long long quad;                         /* quadrature states made (2 per tick) */
	long long ticks;                        /* net A edges */
	/* per sample */
	double drive_sum;
	int drive_n;
} motor_t;

static motor_t motors[2] = {
	{.name = "L", .pwm_port = 'E', .pwm_bit = 3, .in1_bit = 0, .in2_bit = 1,
	 .a_port = 'E', .a_bit = 4, .b_port = 'G', .b_bit = 5, .max_speed = 2100, .mount = 1},
	{.name = "R", .pwm_port = 'H', .pwm_bit = 3, .in1_bit = 2, .in2_bit = 3,
	 .a_port = 'E', .a_bit = 5, .b_port = 'H', .b_bit = 4, .max_speed = 1800, .mount = -1},
};

static void on_pwm(struct avr_irq_t *irq, uint32_t value, void *param) {
	(void)irq;
	motor_t *m = param;
	int v = value != 0;
	if (v == m->pwm) return;
	if (m->pwm) m->high_cycles += avr->cycle - m->pwm_since;
	m->pwm = v;
	m->pwm_since = avr->cycle;
}

static void on_dir(struct avr_irq_t *irq, uint32_t value, void *param) {
	motor_t *m = param;
	int v = value != 0;
	int *pin = (int)irq->irq == m->in1_bit ? &m->in1 : &m->in2;
	if (*pin == v) return;
	*pin = v;
	out("P %llu %s_IN%d %d\n", now_us(), m->name, pin == &m->in1 ? 1 : 2, v);
}

/* An input pin the harness drives: told to the port as its external level too, or simavr
 * would put the pin back to the pull-up's 1 whenever the firmware writes that port. */
static uint8_t ext_mask[26], ext_value[26];

static void drive_input(char port, int bit, avr_irq_t *irq, int level) {
	int k = port - 'A';
	ext_mask[k] |= (uint8_t)(1 << bit);
	ext_value[k] = (uint8_t)((ext_value[k] & ~(1 << bit)) | (level << bit));
	avr_ioport_external_t e = {.name = (unsigned long)port, .mask = ext_mask[k],
	                           .value = ext_value[k]};
	avr_ioctl(avr, AVR_IOCTL_IOPORT_SET_EXTERNAL(port), &e);
	avr_raise_irq(irq, (uint32_t)level);
}

static void set_encoder(motor_t *m) {
	static const int a_of[4] = {0, 1, 1, 0}, b_of[4] = {0, 0, 1, 1};
	int q = (int)(((m->quad % 4) + 4) % 4);
	drive_input(m->a_port, m->a_bit, m->enc_a, a_of[q]);
	drive_input(m->b_port, m->b_bit, m->enc_b, b_of[q]);
}

static void motor_step(motor_t *m, double dt, avr_cycle_count_t step_cycles) {
	if (m->pwm) m->high_cycles += avr->cycle - m->pwm_since;
	m->pwm_since = avr->cycle;
	double duty = (double)m->high_cycles / (double)step_cycles;
	m->high_cycles = 0;
	if (duty > 1) duty = 1;
	int dir = (m->in1 && !m->in2) ? 1 : (m->in2 && !m->in1) ? -1 : 0;
	double u = dir * duty;
	double eff = fabs(u) <= dead_band ? 0 : copysign((fabs(u) - dead_band) / (1 - dead_band), u);
	m->speed += (m->max_speed * eff - m->speed) * dt / tau;
	m->pos += m->speed * dt;
	m->drive_sum += u * m->mount;
	m->drive_n++;
	/* one quadrature state per step at most, so that every edge reaches the firmware's ISR */
	long long want = (long long)floor(m->pos * 2);
	if (want != m->quad) {
		int up = want > m->quad;
		int a_before = (int)((((m->quad % 4) + 4) % 4) == 1 || (((m->quad % 4) + 4) % 4) == 2);
		m->quad += up ? 1 : -1;
		set_encoder(m);
		int a_after = (int)((((m->quad % 4) + 4) % 4) == 1 || (((m->quad % 4) + 4) % 4) == 2);
		if (a_before != a_after) m->ticks += up ? 1 : -1;
	}
}

static avr_cycle_count_t model_timer(struct avr_t *a, avr_cycle_count_t when, void *param) {
	(void)param;
	static unsigned long long next_sample;
	avr_cycle_count_t step = avr_usec_to_cycles(a, STEP_US);
	for (int i = 0; i < 2; i++) motor_step(&motors[i], STEP_US * 1e-6, step);
	unsigned long long t = now_us();
	if (t >= next_sample) {
		next_sample = t + sample_us;
		double d[2];
		for (int i = 0; i < 2; i++) {
			d[i] = motors[i].drive_n ? motors[i].drive_sum / motors[i].drive_n : 0;
			motors[i].drive_sum = 0;
			motors[i].drive_n = 0;
		}
		out("M %llu %.4f %.4f %.2f %.2f %lld %lld\n", t, d[0], d[1],
		    motors[0].speed * motors[0].mount, motors[1].speed * motors[1].mount,
		    motors[0].ticks * motors[0].mount, motors[1].ticks * motors[1].mount);
	}
	return when + step;
}

/* --- frames seen on the wire (for the log; the tests check their content) ------------------ */
typedef struct {
	const char *dir;
	uint8_t buf[64];
	int len;
	unsigned long long t_first;
	int corrupt;                            /* flip a bit in the next frame's 6th byte */
} splitter_t;

static splitter_t rx_split = {.dir = "RX"}, tx_split = {.dir = "TX"};

/* Returns the byte as it goes on (possibly corrupted). */
static uint8_t split(splitter_t *s, uint8_t b) {
	if (s->len == 0 && b != 0xAA) return b;
	if (s->len == 1 && b != 0x55) {
		s->len = b == 0xAA;
		return b;
	}
	if (s->len == 0) s->t_first = now_us();
	if (s->len == 5 && s->corrupt) {
		b ^= 0x10;
		s->corrupt = 0;
		out("I corrupted %s %llu\n", s->dir, now_us());
	}
	s->buf[s->len++] = b;
	if (s->len >= 5 && (s->buf[4] > 32 || s->len == 6 + s->buf[4])) {
		char hex[2 * 64 + 1];
		for (int i = 0; i < s->len; i++) sprintf(hex + 2 * i, "%02x", s->buf[i]);
		out("%s %llu %llu %s\n", s->dir, s->t_first, now_us(), hex);
		s->len = 0;
	}
	return b;
}

/* --- the serial bridge: one thread, the simulation's ------------------------------------------ */
static const char *link_path;
static int master = -1, slave = -1;
static int muted, uart_xon = 1;
static avr_irq_t *uart_in;

static void plug(void) {
	char name[256];
	if (openpty(&master, &slave, name, NULL, NULL) < 0) {
		perror("openpty");
		exit(1);
	}
	struct termios tio;
	tcgetattr(slave, &tio);
	cfmakeraw(&tio);
	tcsetattr(slave, TCSANOW, &tio);
	fcntl(master, F_SETFL, fcntl(master, F_GETFL) | O_NONBLOCK);
	char tmp[4096];
	snprintf(tmp, sizeof tmp, "%s.new", link_path);
	unlink(tmp);
	if (symlink(name, tmp) != 0 || rename(tmp, link_path) != 0) {
		perror(link_path);
		exit(1);
	}
	out("I plugged %s %s\n", link_path, name);
}

static void unplug(void) {
	if (master >= 0) close(master);
	if (slave >= 0) close(slave);
	master = slave = -1;
	unlink(link_path);
	out("I unplugged %llu\n", now_us());
}

static void on_uart_out(struct avr_irq_t *irq, uint32_t value, void *param) {
	(void)irq;
	(void)param;
	uint8_t b = split(&tx_split, (uint8_t)value);
	if (master >= 0 && write(master, &b, 1) < 0 && errno != EAGAIN && errno != EIO)
		perror("pty write");   /* nobody reading: the byte is lost, as on a real wire */
}

static void on_xon(struct avr_irq_t *irq, uint32_t value, void *param) {
	(void)irq; (void)value; (void)param;
	uart_xon = 1;
}

static void on_xoff(struct avr_irq_t *irq, uint32_t value, void *param) {
	(void)irq; (void)value; (void)param;
	uart_xon = 0;
}

static uint8_t pending[256];
static int pending_len, pending_done;

static avr_cycle_count_t next_rx;

static void feed_uart(void) {
	if (pending_done == pending_len && master >= 0) {
		ssize_t n = read(master, pending, sizeof pending);
		pending_len = n > 0 ? (int)n : 0;
		pending_done = 0;
		if (muted) pending_len = 0;
	}
	if (pending_done == pending_len) return;
	if (next_rx < avr->cycle) next_rx = avr->cycle;
	while (uart_xon && pending_done < pending_len && next_rx <= avr->cycle + avr_usec_to_cycles(avr, SERVICE_US / 2)) {
		uint8_t b = split(&rx_split, pending[pending_done++]);
		avr_raise_irq(uart_in, b);
		next_rx += (avr_cycle_count_t)(BYTE_US * avr->frequency / 1e6);
	}
}

static int quit, reset_pending;

static void command(const char *line) {
	if (!strcmp(line, "unplug")) unplug();
	else if (!strncmp(line, "plug", 4)) {
		if (master < 0) plug();
		if (strstr(line, "reset")) reset_pending = 1;
	} else if (!strcmp(line, "mute")) { muted = 1; out("I muted %llu\n", now_us()); }
	else if (!strcmp(line, "unmute")) { muted = 0; out("I unmuted %llu\n", now_us()); }
	else if (!strcmp(line, "corrupt-rx")) rx_split.corrupt = 1;
	else if (!strcmp(line, "corrupt-tx")) tx_split.corrupt = 1;
	else if (!strcmp(line, "quit")) quit = 1;
	else if (line[0]) out("I unknown command %s\n", line);
}

static void read_commands(void) {
	static char line[256];
	static int len;
	struct pollfd p = {.fd = 0, .events = POLLIN};
	while (poll(&p, 1, 0) > 0) {
		char c;
		ssize_t n = read(0, &c, 1);
		if (n <= 0) { quit = 1; return; }   /* the test is gone */
		if (c == '\n') {
			line[len] = 0;
			len = 0;
			command(line);
		} else if (len < (int)sizeof line - 1) line[len++] = c;
	}
}

static struct timespec wall0;

static void pace(void) {
	if (speed_factor <= 0) return;
	struct timespec t;
	clock_gettime(CLOCK_MONOTONIC, &t);
	double wall = (t.tv_sec - wall0.tv_sec) + (t.tv_nsec - wall0.tv_nsec) * 1e-9;
	double ahead = now_us() * 1e-6 / speed_factor - wall;
	if (ahead > 0.0005) {
		struct timespec d = {.tv_sec = (time_t)ahead,
		                     .tv_nsec = (long)((ahead - floor(ahead)) * 1e9)};
		nanosleep(&d, NULL);
	}
}

static avr_cycle_count_t service_timer(struct avr_t *a, avr_cycle_count_t when, void *param) {
	(void)param;
	feed_uart();
	read_commands();
	pace();
	return when + avr_usec_to_cycles(a, SERVICE_US);
}

/* --- setup --------------------------------------------------------------------------------- */
static void quiet_uart(void) {   /* simavr would print the UART's bytes on its console */
	uint32_t f = 0;
	avr_ioctl(avr, AVR_IOCTL_UART_GET_FLAGS('0'), &f);
	f &= ~AVR_UART_FLAG_STDIO;
	avr_ioctl(avr, AVR_IOCTL_UART_SET_FLAGS('0'), &f);
}

static void start_timers(void) {
	avr_cycle_timer_cancel(avr, model_timer, NULL);
	avr_cycle_timer_cancel(avr, service_timer, NULL);
	avr_cycle_timer_register_usec(avr, STEP_US, model_timer, NULL);
	avr_cycle_timer_register_usec(avr, SERVICE_US, service_timer, NULL);
}

static void pair(const char *s, double *a, double *b) {
	if (sscanf(s, "%lf,%lf", a, b) != 2) {
		fprintf(stderr, "expected two numbers A,B: %s\n", s);
		exit(2);
	}
}

typedef struct { const char *name; uint32_t value; uint16_t addr; } poke_t;

int main(int argc, char **argv) {
	const char *elf = NULL;
	poke_t pokes[8];
	int npokes = 0;
	for (int i = 1; i < argc; i++) {
		const char *a = argv[i], *v = i + 1 < argc ? argv[i + 1] : NULL;
		if (a[0] != '-') { elf = a; continue; }
		if (!v) { fprintf(stderr, "%s needs a value\n", a); return 2; }
		i++;
		if (!strcmp(a, "--link")) link_path = v;
		else if (!strcmp(a, "--speed")) speed_factor = atof(v);
		else if (!strcmp(a, "--tau")) tau = atof(v);
		else if (!strcmp(a, "--dead-band")) dead_band = atof(v);
		else if (!strcmp(a, "--sample-ms")) sample_us = (unsigned)(atof(v) * 1000);
		else if (!strcmp(a, "--max-speed")) pair(v, &motors[0].max_speed, &motors[1].max_speed);
		else if (!strcmp(a, "--mount")) {
			double l, r;
			pair(v, &l, &r);
			motors[0].mount = l < 0 ? -1 : 1;
			motors[1].mount = r < 0 ? -1 : 1;
		} else if (!strcmp(a, "--set") && npokes < 8) {
			const char *eq = strchr(v, '=');
			if (!eq) { fprintf(stderr, "--set SYMBOL=VALUE: %s\n", v); return 2; }
			pokes[npokes].name = strndup(v, (size_t)(eq - v));
			pokes[npokes].value = (uint32_t)strtoll(eq + 1, NULL, 0);
			npokes++;
		} else { fprintf(stderr, "unknown option %s\n", a); return 2; }
	}
	if (!elf || !link_path) {
		fprintf(stderr, "usage: %s FIRMWARE.elf --link PATH [options] (see the source)\n", argv[0]);
		return 2;
	}
	avr_global_logger_set(quiet_logger);
	elf_firmware_t fw;
	memset(&fw, 0, sizeof fw);
	if (elf_read_firmware(elf, &fw) != 0) {
		fprintf(stderr, "cannot read %s\n", elf);
		return 1;
	}
	strcpy(fw.mmcu, "atmega2560");
	fw.frequency = 16000000;
	avr = avr_make_mcu_by_name(fw.mmcu);
	if (!avr) return 1;
	avr_init(avr);
	avr_load_firmware(avr, &fw);
	avr->frequency = fw.frequency;

	/* the addresses of main() and of the variables to set */
	uint32_t main_pc = 0;
	for (uint32_t i = 0; i < fw.symbolcount; i++) {
		const avr_symbol_t *s = fw.symbol[i];
		if (!strcmp(s->symbol, "main")) main_pc = s->addr;
		for (int k = 0; k < npokes; k++)
			if (!strcmp(s->symbol, pokes[k].name)) pokes[k].addr = (uint16_t)(s->addr & 0xffff);
	}
	for (int k = 0; k < npokes; k++)
		if (!pokes[k].addr) { fprintf(stderr, "no symbol %s in %s\n", pokes[k].name, elf); return 1; }
	if (npokes && !main_pc) { fprintf(stderr, "no main() in %s\n", elf); return 1; }

	/* pins */
	for (int i = 0; i < 2; i++) {
		motor_t *m = &motors[i];
		avr_irq_register_notify(avr_io_getirq(avr, AVR_IOCTL_IOPORT_GETIRQ(m->pwm_port), m->pwm_bit),
		                        on_pwm, m);
		avr_irq_register_notify(avr_io_getirq(avr, AVR_IOCTL_IOPORT_GETIRQ('A'), m->in1_bit), on_dir, m);
		avr_irq_register_notify(avr_io_getirq(avr, AVR_IOCTL_IOPORT_GETIRQ('A'), m->in2_bit), on_dir, m);
	}
	for (int i = 0; i < 2; i++) {
		motor_t *m = &motors[i];
		m->enc_a = avr_io_getirq(avr, AVR_IOCTL_IOPORT_GETIRQ(m->a_port), m->a_bit);
		m->enc_b = avr_io_getirq(avr, AVR_IOCTL_IOPORT_GETIRQ(m->b_port), m->b_bit);
		set_encoder(m);
	}

	/* the serial port */
	quiet_uart();
	uart_in = avr_io_getirq(avr, AVR_IOCTL_UART_GETIRQ('0'), UART_IRQ_INPUT);
	avr_irq_register_notify(avr_io_getirq(avr, AVR_IOCTL_UART_GETIRQ('0'), UART_IRQ_OUTPUT),
	                        on_uart_out, NULL);
	avr_irq_register_notify(avr_io_getirq(avr, AVR_IOCTL_UART_GETIRQ('0'), UART_IRQ_OUT_XON),
	                        on_xon, NULL);
	avr_irq_register_notify(avr_io_getirq(avr, AVR_IOCTL_UART_GETIRQ('0'), UART_IRQ_OUT_XOFF),
	                        on_xoff, NULL);
	plug();

	start_timers();
	clock_gettime(CLOCK_MONOTONIC, &wall0);
	out("I ready %s\n", link_path);

	int poked = npokes == 0;
	while (!quit) {
		if (!poked && avr->pc == main_pc) {
			for (int k = 0; k < npokes; k++) {
				uint32_t v = pokes[k].value;
				for (int b = 0; b < 4; b++) avr->data[pokes[k].addr + b] = (uint8_t)(v >> (8 * b));
				out("I set %s=%u at %llu\n", pokes[k].name, v, now_us());
			}
			poked = 1;
		}
		if (reset_pending) {
			avr_cycle_count_t before = avr->cycle;
			avr_reset(avr);
			cycle_base += before - avr->cycle;
			/* every pin is an input after a reset: nothing drives the motors */
			for (int i = 0; i < 2; i++) {
				motor_t *m = &motors[i];
				m->pwm = 0;
				m->pwm_since = avr->cycle;
				if (m->in1) out("P %llu %s_IN1 0\n", now_us(), m->name);
				if (m->in2) out("P %llu %s_IN2 0\n", now_us(), m->name);
				m->in1 = m->in2 = 0;
			}
			next_rx = avr->cycle;
			quiet_uart();
			for (int i = 0; i < 2; i++) set_encoder(&motors[i]);
			start_timers();
			reset_pending = 0;
			out("I reset %llu\n", now_us());
		}
		int state = avr_run(avr);
		if (state == cpu_Done || state == cpu_Crashed) {
			out("I stopped state %d at %llu\n", state, now_us());
			break;
		}
	}
	unplug();
	return 0;
}
