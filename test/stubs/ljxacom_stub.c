/* A stand-in for Keyence's libljxacom.so with the functions profiler_driver's ljx backend calls, serving
 * profiles from a file in high-speed mode (test/test_ljx_backend.py builds and loads it).
 *
 * LJX_STUB_PROFILES: file of uint32 count, uint32 points, int32 x_start, int32 x_pitch (0.01 um),
 *                    then count * points int32 heights (0.01 um, INT32_MIN = invalid).
 * LJX_STUB_RATE_HZ:  profiles per second (default 200).
 * LJX_STUB_INTERRUPT_AFTER: after this many profiles, report an interruption (notify 0x1) once.
 */
#include <pthread.h>
#include <stdint.h>
#include <stdio.h>
#include <stdlib.h>
#include <string.h>
#include <time.h>

typedef struct { unsigned char abyIpAddress[4]; unsigned short wPortNo; unsigned char reserve[2]; } EthernetConfig;
typedef struct {
  unsigned char byProfileCount, reserve1, byLuminanceOutput, reserve2;
  unsigned short wProfileDataCount; unsigned char reserve3[2];
  int lXStart, lXPitch;
} ProfileInfo;
typedef struct { unsigned char bySendPosition; unsigned char reserve[3]; } PreStartRequest;
typedef void (*Callback)(unsigned char *, unsigned int, unsigned int, unsigned int, unsigned int);

static Callback callback_;
static uint32_t count_, points_;
static int32_t x_start_, x_pitch_;
static int32_t *heights_;
static volatile int running_;
static pthread_t thread_;
static int open_;
static long interrupt_after_ = -1;
static uint32_t trigger_ = 0;

static int load(void) {
  const char *path = getenv("LJX_STUB_PROFILES");
  FILE *f = path ? fopen(path, "rb") : NULL;
  if (!f) return -1;
  uint32_t header[4];
  if (fread(header, 4, 4, f) != 4) { fclose(f); return -1; }
  count_ = header[0]; points_ = header[1]; x_start_ = (int32_t)header[2]; x_pitch_ = (int32_t)header[3];
  free(heights_);
  heights_ = malloc((size_t)count_ * points_ * 4);
  size_t got = fread(heights_, 4, (size_t)count_ * points_, f);
  fclose(f);
  return got == (size_t)count_ * points_ ? 0 : -1;
}

static void *stream(void *unused) {
  (void)unused;
  const char *rate_text = getenv("LJX_STUB_RATE_HZ");
  double rate = rate_text ? atof(rate_text) : 200.0;
  struct timespec period = {0, (long)(1e9 / rate)};
  unsigned int unit = 24 + 4 * points_ + 4;
  unsigned char *buffer = calloc(1, unit);
  long sent = 0;
  while (running_) {
    nanosleep(&period, NULL);
    if (interrupt_after_ >= 0 && sent == interrupt_after_) {
      interrupt_after_ = -1;
      callback_(buffer, unit, 0, 0x1, 0);  /* high-speed communication interrupted */
      break;
    }
    trigger_++;
    memset(buffer, 0, 24);
    memcpy(buffer + 4, &trigger_, 4);
    memcpy(buffer + 24, heights_ + (size_t)(trigger_ % count_) * points_, 4 * points_);
    callback_(buffer, unit, 1, 0, 0);
    sent++;
  }
  free(buffer);
  return NULL;
}

long LJX8IF_Initialize(void) { return 0; }
long LJX8IF_Finalize(void) { return 0; }

int LJX8IF_EthernetOpen(int id, EthernetConfig *config) {
  (void)id;
  if (config->abyIpAddress[0] != 127) return 0x1000;  /* only loopback in tests */
  if (load() != 0) return 0x1001;
  const char *after = getenv("LJX_STUB_INTERRUPT_AFTER");
  if (after && open_ == 0) interrupt_after_ = atol(after);
  open_++;
  return 0;
}

int LJX8IF_CommunicationClose(int id) { (void)id; return 0; }

int LJX8IF_InitializeHighSpeedDataCommunication(int id, EthernetConfig *config, unsigned short port, Callback cb,
                                                unsigned int per_call, unsigned int thread_id) {
  (void)id; (void)config; (void)port; (void)per_call; (void)thread_id;
  callback_ = cb;
  return 0;
}

int LJX8IF_PreStartHighSpeedDataCommunication(int id, PreStartRequest *request, ProfileInfo *info) {
  (void)id; (void)request;
  memset(info, 0, sizeof(*info));
  info->byProfileCount = 1;
  info->wProfileDataCount = (unsigned short)points_;
  info->lXStart = x_start_;
  info->lXPitch = x_pitch_;
  return 0;
}

int LJX8IF_StartHighSpeedDataCommunication(int id) {
  (void)id;
  running_ = 1;
  return pthread_create(&thread_, NULL, stream, NULL) == 0 ? 0 : 0x1002;
}

int LJX8IF_StopHighSpeedDataCommunication(int id) {
  (void)id;
  if (running_) { running_ = 0; pthread_join(thread_, NULL); }
  return 0;
}

int LJX8IF_FinalizeHighSpeedDataCommunication(int id) { (void)id; return 0; }
