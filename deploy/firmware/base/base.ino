// mrslam motor base firmware (Arduino Mega 2560, ATmega2560 at 16 MHz): two DC motors with
// quadrature encoders behind an L298N-style H-bridge (a PWM enable and two direction inputs per
// motor). Protocol and wiring: deploy/firmware/README.md. Frames 0xAA 0x55 | type | seq | len |
// payload | crc8.
//   host -> board  SPEED 0x01: int32 left, int32 right [ticks/s], uint16 timeout [ms]
//                  STOP  0x02
//   board -> host  ENCODERS 0x81 every 20 ms: uint32 ms, int32 left, int32 right, uint8 flags
// Safety: motors stop when the SPEED's timeout passes without a new valid frame, on STOP, and
// at once after any frame with a bad checksum, an impossible length or an unknown type, or a
// frame cut off in the middle.
//
// Plain avr-libc, no Arduino core: `make -C deploy/firmware` builds it (see the Makefile there);
// the .ino name is kept so the file sits where the Arduino tools would look for it.

#include <avr/interrupt.h>
#include <avr/io.h>
#include <stdint.h>
#include <string.h>

// --- wiring ----------------------------------------------------------------------------------
// Arduino pin -> AVR port bit:
//   left  PWM  D5  = PE3 (OC3A, Timer3)     right PWM  D6 = PH3 (OC4A, Timer4)
//   left  IN1  D22 = PA0, IN2 D23 = PA1     right IN1 D24 = PA2, IN2 D25 = PA3
//   left  encoder A D2 = PE4 (INT4), B D4 = PG5
//   right encoder A D3 = PE5 (INT5), B D7 = PH4
// Which way each motor turns for "forward": +1 drives IN1 high for forward and counts encoder
// A-leads-B as forward; -1 (a mirror-mounted motor) the opposite.
const int8_t L_SIGN = 1, R_SIGN = -1;

// --- speed control: feed-forward plus PI, output a duty in [-1, 1] ----------------------------
// The feed-forward KFF * target does most of the work; the PI corrects the wheel's deviation
// from the response expected of it (the target filtered by the motor's time constant TAU_S),
// so that it only acts on what the feed-forward got wrong (load, friction, a weaker motor) and
// does not wind up while the wheel accelerates. Defaults to calibrate on the real base
// (README "Calibrating"): KFF is 1 / (wheel ticks/s at full duty), TAU_S the time the wheel
// takes to reach 63 % of a step in speed, KP duty per tick/s of deviation, KI duty per tick.
const float KFF = 1.0f / 2000.0f, TAU_S = 0.1f, KP = 0.0004f, KI = 0.004f;
const uint16_t CONTROL_MS = 20;            // control step and ENCODERS period
const uint16_t MAX_TIMEOUT_MS = 500;       // the longest a SPEED may hold
const uint16_t RX_GAP_MS = 20;             // a frame whose bytes stop this long is cut off
const uint16_t PWM_TOP = 799;              // 16 MHz / (1 + 799) = 20 kHz PWM

const uint8_t T_SPEED = 0x01, T_STOP = 0x02, T_ENCODERS = 0x81;
const uint8_t F_TIMEOUT = 1, F_BAD_FRAME = 2, F_DRIVING = 4;
const uint8_t MAX_PAYLOAD = 32;

// --- time and encoders (interrupts) ----------------------------------------------------------
// Counters are unsigned so that they wrap modulo 2^32 (signed overflow is undefined in C++);
// ENCODERS sends the same 32 bits as int32.
volatile uint32_t boardMs = 0;
volatile uint32_t leftTicks = 0, rightTicks = 0;

ISR(TIMER1_COMPA_vect) { boardMs = boardMs + 1; }

// Both edges of A are counted: A != B after an edge means A leads B (forward for sign +1).
ISR(INT4_vect) {
  bool a = PINE & _BV(PE4), b = PING & _BV(PG5);
  leftTicks = leftTicks + (uint32_t)(int32_t)((a != b) ? L_SIGN : -L_SIGN);
}

ISR(INT5_vect) {
  bool a = PINE & _BV(PE5), b = PINH & _BV(PH4);
  rightTicks = rightTicks + (uint32_t)(int32_t)((a != b) ? R_SIGN : -R_SIGN);
}

uint32_t atomicRead(const volatile uint32_t &v) {
  uint8_t s = SREG;
  cli();
  uint32_t x = v;
  SREG = s;
  return x;
}

// --- serial (USART0, the Mega's USB port) with interrupt-driven ring buffers -----------------
const uint8_t RING = 64;   // a power of two
volatile uint8_t rxBuf[RING], txBuf[RING];
volatile uint8_t rxHead = 0, rxTail = 0, txHead = 0, txTail = 0;

ISR(USART0_RX_vect) {
  uint8_t b = UDR0;
  uint8_t next = (rxHead + 1) & (RING - 1);
  if (next != rxTail) {     // full: the byte is lost, and the frame it belonged to fails
    rxBuf[rxHead] = b;
    rxHead = next;
  }
}

ISR(USART0_UDRE_vect) {
  if (txHead == txTail) {
    UCSR0B &= (uint8_t)~_BV(UDRIE0);
    return;
  }
  UDR0 = txBuf[txTail];
  txTail = (txTail + 1) & (RING - 1);
}

void serialBegin() {
  UCSR0A = _BV(U2X0);
  UBRR0 = 16;                                   // 115200 baud with U2X at 16 MHz (as Arduino)
  UCSR0C = _BV(UCSZ01) | _BV(UCSZ00);           // 8N1
  UCSR0B = _BV(RXEN0) | _BV(TXEN0) | _BV(RXCIE0);
}

int serialRead() {
  if (rxHead == rxTail) return -1;
  uint8_t b = rxBuf[rxTail];
  rxTail = (rxTail + 1) & (RING - 1);
  return b;
}

void serialWrite(const uint8_t *p, uint8_t n) {
  while (n--) {
    uint8_t next = (txHead + 1) & (RING - 1);
    while (next == txTail) {}                   // wait for room (never at 19 bytes per 20 ms)
    txBuf[txHead] = *p++;
    txHead = next;
    UCSR0B |= _BV(UDRIE0);
  }
}

// --- frames ----------------------------------------------------------------------------------
uint8_t crc8(const uint8_t *p, uint8_t n) {        // polynomial 0x07, init 0
  uint8_t c = 0;
  while (n--) {
    c ^= *p++;
    for (uint8_t i = 0; i < 8; i++) c = (c & 0x80) ? (uint8_t)((c << 1) ^ 0x07) : (uint8_t)(c << 1);
  }
  return c;
}

// --- motors ----------------------------------------------------------------------------------
int32_t targetL = 0, targetR = 0;          // ticks/s
uint32_t deadline = 0;                     // boardMs at which the SPEED lapses
float integL = 0, integR = 0;              // accumulated speed deviation [ticks]
float expectL = 0, expectR = 0;            // the speed expected by now [ticks/s]
uint8_t flags = 0, txSeq = 0;
bool driven = false;                       // motors driven since the last report

// out in [-1, 1], already in the motor's own direction.
void driveLeft(float out) {
  uint16_t duty = (uint16_t)((out < 0 ? -out : out) * PWM_TOP + 0.5f);
  if (duty == 0) {
    TCCR3A &= (uint8_t)~_BV(COM3A1);       // the pin back to PORTE = low: no pulse at all
    PORTE &= (uint8_t)~_BV(PE3);
    PORTA &= (uint8_t)~(_BV(PA0) | _BV(PA1));
    return;
  }
  PORTA = (uint8_t)((PORTA & ~(_BV(PA0) | _BV(PA1))) | (out > 0 ? _BV(PA0) : _BV(PA1)));
  if (duty >= PWM_TOP) {                  // full duty: a steady high, not a compare at TOP
    PORTE |= _BV(PE3);
    TCCR3A &= (uint8_t)~_BV(COM3A1);
  } else {
    OCR3A = duty;
    TCCR3A |= _BV(COM3A1);
  }
}

void driveRight(float out) {
  uint16_t duty = (uint16_t)((out < 0 ? -out : out) * PWM_TOP + 0.5f);
  if (duty == 0) {
    TCCR4A &= (uint8_t)~_BV(COM4A1);       // the pin back to PORTH = low: no pulse at all
    PORTH &= (uint8_t)~_BV(PH3);
    PORTA &= (uint8_t)~(_BV(PA2) | _BV(PA3));
    return;
  }
  PORTA = (uint8_t)((PORTA & ~(_BV(PA2) | _BV(PA3))) | (out > 0 ? _BV(PA2) : _BV(PA3)));
  if (duty >= PWM_TOP) {                  // full duty: a steady high, not a compare at TOP
    PORTH |= _BV(PH3);
    TCCR4A &= (uint8_t)~_BV(COM4A1);
  } else {
    OCR4A = duty;
    TCCR4A |= _BV(COM4A1);
  }
}

void stopMotors() {
  targetL = targetR = 0;
  integL = integR = 0;
  expectL = expectR = 0;
  driveLeft(0);
  driveRight(0);
}

float clampf(float x, float lo, float hi) { return x < lo ? lo : (x > hi ? hi : x); }

// One control step for one wheel: returns the duty in the wheel's forward direction.
float control(int32_t target, float measured, float &expect, float &integ) {
  const float dt = CONTROL_MS / 1000.0f;
  expect += ((float)target - expect) * dt / (TAU_S + dt);
  float e = expect - measured;
  integ = clampf(integ + e * dt, -1.0f / KI, 1.0f / KI);
  return clampf(KFF * (float)target + KP * e + KI * integ, -1.0f, 1.0f);
}

// --- receiving -------------------------------------------------------------------------------
uint8_t rx[5 + MAX_PAYLOAD + 1];
uint8_t rxLen = 0;
uint32_t rxLastMs = 0;

void badFrame() {
  flags |= F_BAD_FRAME;
  stopMotors();
  rxLen = 0;
}

void handle(uint8_t type, const uint8_t *payload, uint8_t n) {
  if (type == T_SPEED && n == 10) {
    int32_t l, r;
    uint16_t t;
    memcpy(&l, payload, 4);
    memcpy(&r, payload + 4, 4);
    memcpy(&t, payload + 8, 2);
    if (t > MAX_TIMEOUT_MS) t = MAX_TIMEOUT_MS;
    targetL = l;
    targetR = r;
    deadline = atomicRead(boardMs) + t;
    if (l == 0 && r == 0) stopMotors();
  } else if (type == T_STOP && n == 0) {
    stopMotors();
  } else {
    badFrame();
  }
}

void receive(uint32_t now) {
  if (rxLen > 0 && (uint32_t)(now - rxLastMs) >= RX_GAP_MS) badFrame();   // cut off
  int c;
  while ((c = serialRead()) >= 0) {
    uint8_t b = (uint8_t)c;
    rxLastMs = now;
    if (rxLen == 0 && b != 0xAA) continue;
    if (rxLen == 1 && b != 0x55) {
      rxLen = (b == 0xAA);
      continue;
    }
    rx[rxLen++] = b;
    if (rxLen == 5 && rx[4] > MAX_PAYLOAD) {
      badFrame();
      continue;
    }
    if (rxLen >= 6 && rxLen == 6 + rx[4]) {
      uint8_t n = rx[4];
      rxLen = 0;
      if (crc8(rx + 2, 3 + n) == rx[5 + n]) handle(rx[2], rx + 5, n);
      else badFrame();
    }
  }
}

// --- sending ---------------------------------------------------------------------------------
void sendEncoders(uint32_t now, uint32_t l, uint32_t r) {
  uint8_t f[6 + 13];
  f[0] = 0xAA;
  f[1] = 0x55;
  f[2] = T_ENCODERS;
  f[3] = txSeq++;
  f[4] = 13;
  memcpy(f + 5, &now, 4);
  memcpy(f + 9, &l, 4);
  memcpy(f + 13, &r, 4);
  f[17] = flags | (driven ? F_DRIVING : 0);
  f[18] = crc8(f + 2, 3 + 13);
  serialWrite(f, sizeof f);
  flags = 0;
}

void setup() {
  // direction pins and PWM pins as outputs, low
  DDRA |= _BV(PA0) | _BV(PA1) | _BV(PA2) | _BV(PA3);
  DDRE |= _BV(PE3);
  DDRH |= _BV(PH3);
  // encoder inputs with pull-ups (open-collector encoders)
  DDRE &= (uint8_t)~(_BV(PE4) | _BV(PE5));
  PORTE |= _BV(PE4) | _BV(PE5);
  DDRG &= (uint8_t)~_BV(PG5);
  PORTG |= _BV(PG5);
  DDRH &= (uint8_t)~_BV(PH4);
  PORTH |= _BV(PH4);
  // Timer1: 1 kHz tick (CTC, 16 MHz / 64 / 250)
  TCCR1A = 0;
  TCCR1B = _BV(WGM12) | _BV(CS11) | _BV(CS10);
  OCR1A = 249;
  TIMSK1 = _BV(OCIE1A);
  // Timers 3 and 4: fast PWM with TOP = ICR (mode 14), no prescaler; output connected on demand
  TCCR3A = _BV(WGM31);
  TCCR3B = _BV(WGM33) | _BV(WGM32) | _BV(CS30);
  ICR3 = PWM_TOP;
  TCCR4A = _BV(WGM41);
  TCCR4B = _BV(WGM43) | _BV(WGM42) | _BV(CS40);
  ICR4 = PWM_TOP;
  // INT4, INT5 on any edge of encoder A
  EICRB = _BV(ISC40) | _BV(ISC50);
  EIFR = _BV(INTF4) | _BV(INTF5);
  EIMSK = _BV(INT4) | _BV(INT5);
  serialBegin();
  stopMotors();
}

int main() {
  setup();
  sei();
  uint32_t lastControl = atomicRead(boardMs);
  uint32_t lastL = atomicRead(leftTicks), lastR = atomicRead(rightTicks);
  for (;;) {
    uint32_t now = atomicRead(boardMs);
    receive(now);
    if ((targetL || targetR) && (int32_t)(now - deadline) >= 0) {
      flags |= F_TIMEOUT;
      stopMotors();
    }
    if ((uint32_t)(now - lastControl) < CONTROL_MS) continue;
    // keep a 20 ms grid; start a new one after a jump of the clock (more than a step behind)
    lastControl = (uint32_t)(now - lastControl) < 2 * CONTROL_MS ? lastControl + CONTROL_MS : now;
    uint32_t l = atomicRead(leftTicks), r = atomicRead(rightTicks);
    if (targetL || targetR) {
      const float perS = 1000.0f / CONTROL_MS;
      float measuredL = (float)(int32_t)(l - lastL) * perS;
      float measuredR = (float)(int32_t)(r - lastR) * perS;
      driveLeft(L_SIGN * control(targetL, measuredL, expectL, integL));
      driveRight(R_SIGN * control(targetR, measuredR, expectR, integR));
      driven = true;
    }
    lastL = l;
    lastR = r;
    sendEncoders(now, l, r);
    driven = targetL || targetR;
  }
}
