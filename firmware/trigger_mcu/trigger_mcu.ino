// trigger_mcu: turns the robot controller's per-cycle digital output into the profiler's two trigger
// pulses, and tells the host which trigger fired when (see README.md for wiring, timing and protocol).
//
// Host protocol (ASCII lines, '\n'-terminated, 1,000,000 baud 8N1):
//   MCU -> host: "T <seq> <micros>" per fired trigger, "PONG <micros>", "OK <command>",
//                "READY trigger_mcu 1" at boot and after RESET, "E <text>" for an unknown command.
//   host -> MCU: PING, RESET (sequence back to 0), ARM, DISARM (robot edges are ignored while disarmed).

#include <Arduino.h>

static const uint8_t ROBOT_PIN = 2;        // INT0, from the robot's output through an optocoupler
static const uint8_t TRIGGER_A_PIN = 4;    // PD4 -> profiler trigger input 1 (through a driver transistor)
static const uint8_t TRIGGER_B_PIN = 5;    // PD5 -> profiler trigger input 2
static const uint8_t PULSE_US = 20;        // LJ-X8000 trigger inputs need >= 10 us
static const unsigned long BAUD = 1000000UL;
static const uint8_t QUEUE = 16;           // triggers waiting to be reported (power of two)

struct Fired { uint32_t seq; uint32_t micros; };

static volatile Fired queue_[QUEUE];
static volatile uint8_t head_ = 0, tail_ = 0;
static volatile uint32_t seq_ = 0;
static volatile bool armed_ = true;        // boots armed: a cell without the host driver still triggers
static volatile uint16_t overflows_ = 0;   // reports lost because the host link was too slow

static char line_[24];
static uint8_t length_ = 0;

// The edge: pulse both trigger outputs together (one port write) and note the time. Runs with
// interrupts off, so the pulse width is exact; 20 us is well inside a 1 ms cycle.
static void onRobotEdge() {
  if (!armed_) return;
  uint32_t now = micros();
  PORTD |= _BV(PD4) | _BV(PD5);
  delayMicroseconds(PULSE_US);
  PORTD &= ~(_BV(PD4) | _BV(PD5));
  seq_++;
  uint8_t next = (head_ + 1) & (QUEUE - 1);
  if (next == tail_) { overflows_++; return; }
  queue_[head_].seq = seq_;
  queue_[head_].micros = now;
  head_ = next;
}

static void ready() {
  Serial.println(F("READY trigger_mcu 1"));
}

static void command(const char *text) {
  if (strcmp(text, "PING") == 0) {
    Serial.print(F("PONG "));
    Serial.println(micros());
  } else if (strcmp(text, "RESET") == 0) {
    noInterrupts();
    seq_ = 0;
    head_ = tail_ = 0;
    interrupts();
    Serial.println(F("OK RESET"));
    ready();
  } else if (strcmp(text, "ARM") == 0) {
    armed_ = true;
    Serial.println(F("OK ARM"));
  } else if (strcmp(text, "DISARM") == 0) {
    armed_ = false;
    Serial.println(F("OK DISARM"));
  } else {
    Serial.print(F("E unknown command "));
    Serial.println(text);
  }
}

void setup() {
  pinMode(TRIGGER_A_PIN, OUTPUT);
  pinMode(TRIGGER_B_PIN, OUTPUT);
  digitalWrite(TRIGGER_A_PIN, LOW);
  digitalWrite(TRIGGER_B_PIN, LOW);
  pinMode(ROBOT_PIN, INPUT_PULLUP);
  Serial.begin(BAUD);
  attachInterrupt(digitalPinToInterrupt(ROBOT_PIN), onRobotEdge, FALLING);  // optocoupler pulls low
  ready();
}

void loop() {
  while (tail_ != head_) {  // report fired triggers first: the host stamps profiles with them
    noInterrupts();
    Fired fired = {queue_[tail_].seq, queue_[tail_].micros};
    tail_ = (tail_ + 1) & (QUEUE - 1);
    interrupts();
    Serial.print(F("T "));
    Serial.print(fired.seq);
    Serial.print(' ');
    Serial.println(fired.micros);
  }
  while (Serial.available() > 0) {
    char c = (char)Serial.read();
    if (c == '\r') continue;
    if (c == '\n') {
      line_[length_] = '\0';
      if (length_ > 0) command(line_);
      length_ = 0;
    } else if (length_ < sizeof(line_) - 1) {
      line_[length_++] = c;
    } else {
      length_ = 0;  // an overlong line is noise: drop it
    }
  }
}
