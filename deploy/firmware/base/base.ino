// mrslam motor base firmware (Arduino Mega 2560): two DC motors with quadrature encoders.
// Protocol: deploy/firmware/README.md. Frames 0xAA 0x55 | type | seq | len | payload | crc8.
//   host -> board  SPEED 0x01: int32 left, int32 right [ticks/s], uint16 timeout [ms]
//                  STOP  0x02
//   board -> host  ENCODERS 0x81 every 20 ms: uint32 ms, int32 left, int32 right, uint8 flags
// Safety: motors stop when the SPEED's timeout passes without a new valid frame, on STOP, and
// at once after any frame with a bad checksum or length.

#include <Arduino.h>

// --- wiring (an L298N-style driver: PWM + two direction pins per motor) -----------------------
const uint8_t L_PWM = 5, L_IN1 = 22, L_IN2 = 23;
const uint8_t R_PWM = 6, R_IN1 = 24, R_IN2 = 25;
const uint8_t L_ENC_A = 2, L_ENC_B = 4;     // A on an interrupt pin
const uint8_t R_ENC_A = 3, R_ENC_B = 7;
const int8_t L_SIGN = 1, R_SIGN = -1;       // mirror-mounted motors: forward is opposite

// --- speed control: PI on ticks/s, plus feed-forward -------------------------------------------
const float KP = 0.08f, KI = 0.6f, KFF = 0.05f;     // PWM per tick/s; tune per robot
const uint16_t CONTROL_MS = 20;
const uint16_t MAX_TIMEOUT_MS = 500;

const uint8_t T_SPEED = 0x01, T_STOP = 0x02, T_ENCODERS = 0x81;
const uint8_t F_TIMEOUT = 1, F_BAD_FRAME = 2, F_DRIVING = 4;

volatile int32_t leftTicks = 0, rightTicks = 0;
int32_t targetL = 0, targetR = 0;           // ticks/s
uint32_t deadline = 0;
float integL = 0, integR = 0;
int32_t lastL = 0, lastR = 0;
uint32_t lastControl = 0;
uint8_t flags = 0, txSeq = 0;

void onLeft()  { leftTicks  += (digitalRead(L_ENC_B) ? -1 : 1) * L_SIGN; }
void onRight() { rightTicks += (digitalRead(R_ENC_B) ? -1 : 1) * R_SIGN; }

uint8_t crc8(const uint8_t *p, uint8_t n) {        // polynomial 0x07, init 0
  uint8_t c = 0;
  while (n--) {
    c ^= *p++;
    for (uint8_t i = 0; i < 8; i++) c = (c & 0x80) ? (uint8_t)((c << 1) ^ 0x07) : (uint8_t)(c << 1);
  }
  return c;
}

void drive(uint8_t pwmPin, uint8_t in1, uint8_t in2, float u) {
  int pwm = constrain((int)fabs(u), 0, 255);
  digitalWrite(in1, u > 0);
  digitalWrite(in2, u < 0);
  analogWrite(pwmPin, pwm);
}

void stopMotors() {
  targetL = targetR = 0;
  integL = integR = 0;
  drive(L_PWM, L_IN1, L_IN2, 0);
  drive(R_PWM, R_IN1, R_IN2, 0);
}

// --- receiving ---------------------------------------------------------------------------
uint8_t rx[5 + 32 + 1];
uint8_t rxLen = 0;

void badFrame() {
  flags |= F_BAD_FRAME;
  stopMotors();
  rxLen = 0;
}

void handle(uint8_t type, const uint8_t *payload, uint8_t n) {
  if (type == T_SPEED && n == 10) {
    int32_t l, r; uint16_t t;
    memcpy(&l, payload, 4); memcpy(&r, payload + 4, 4); memcpy(&t, payload + 8, 2);
    targetL = l; targetR = r;
    deadline = millis() + min(t, MAX_TIMEOUT_MS);
  } else if (type == T_STOP) {
    stopMotors();
  } else {
    badFrame();
  }
}

void receive() {
  while (Serial.available()) {
    uint8_t b = Serial.read();
    if (rxLen == 0 && b != 0xAA) continue;
    if (rxLen == 1 && b != 0x55) { rxLen = (b == 0xAA); continue; }
    rx[rxLen++] = b;
    if (rxLen == 5 && rx[4] > 32) { badFrame(); continue; }
    if (rxLen >= 6 && rxLen == 6 + rx[4]) {
      if (crc8(rx + 2, 3 + rx[4]) == rx[5 + rx[4]]) handle(rx[2], rx + 5, rx[4]);
      else badFrame();
      rxLen = 0;
    }
  }
}

// --- sending ------------------------------------------------------------------------------
void sendEncoders(uint32_t now, int32_t l, int32_t r) {
  uint8_t f[6 + 13];
  f[0] = 0xAA; f[1] = 0x55; f[2] = T_ENCODERS; f[3] = txSeq++; f[4] = 13;
  memcpy(f + 5, &now, 4); memcpy(f + 9, &l, 4); memcpy(f + 13, &r, 4);
  f[17] = flags | ((targetL || targetR) ? F_DRIVING : 0);
  f[18] = crc8(f + 2, 3 + 13);
  Serial.write(f, sizeof f);
  flags = 0;
}

void setup() {
  Serial.begin(115200);
  for (uint8_t p : {L_PWM, L_IN1, L_IN2, R_PWM, R_IN1, R_IN2}) pinMode(p, OUTPUT);
  pinMode(L_ENC_A, INPUT_PULLUP); pinMode(L_ENC_B, INPUT_PULLUP);
  pinMode(R_ENC_A, INPUT_PULLUP); pinMode(R_ENC_B, INPUT_PULLUP);
  attachInterrupt(digitalPinToInterrupt(L_ENC_A), onLeft, RISING);
  attachInterrupt(digitalPinToInterrupt(R_ENC_A), onRight, RISING);
  stopMotors();
}

void loop() {
  receive();
  uint32_t now = millis();
  if ((targetL || targetR) && (int32_t)(now - deadline) > 0) {
    flags |= F_TIMEOUT;
    stopMotors();
  }
  if (now - lastControl < CONTROL_MS) return;
  float dt = (now - lastControl) / 1000.0f;
  lastControl = now;
  noInterrupts();
  int32_t l = leftTicks, r = rightTicks;
  interrupts();
  if (targetL || targetR) {
    float eL = targetL - (l - lastL) / dt, eR = targetR - (r - lastR) / dt;
    integL = constrain(integL + eL * dt, -400, 400);
    integR = constrain(integR + eR * dt, -400, 400);
    drive(L_PWM, L_IN1, L_IN2, L_SIGN * (KFF * targetL + KP * eL + KI * integL));
    drive(R_PWM, R_IN1, R_IN2, R_SIGN * (KFF * targetR + KP * eR + KI * integR));
  }
  lastL = l; lastR = r;
  sendEncoders(now, l, r);
}
