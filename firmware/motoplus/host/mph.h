/*
 * mph: the host side of host/motoPlus.h, as sim_cell's controller (through ctypes) and the fuzzer drive
 * it. The interpolation clock ticks when the simulation says so; mpExRcsIncrementMove adds to an offset
 * the simulation reads back and applies to its arm; mpGetCartPos returns the pose the simulation set;
 * D variables and status signals are what the simulation configured.
 */
#ifndef MPH_H
#define MPH_H

#include <stdint.h>

void mph_reset(void);                          /* before configuring a fresh controller */
void mph_set_var_d(int index, int32_t value);
void mph_set_io(uint32_t address, int value);
void mph_set_bind_address(const char *ipv4);   /* the host build listens here (default 127.0.0.1) */
void mph_set_bind_port(int port);              /* and on this port, not the configured one (0: any free one) */
void mph_set_cart_pos(const int32_t pose[6]);
void mph_set_motion_error(int code);           /* mpExRcsIncrementMove's answer from now on (0: accepted) */
/* Network faults on what the controller sends: every STATE dropped with this probability, every frame
 * delayed this long, the link broken after this many STATEs (0: never; once). */
void mph_set_net_faults(double state_drop, uint32_t delay_us, uint32_t fail_after_states, uint64_t seed);

int mph_start(void);                           /* runs mpUsrRoot; 0 when both tasks run */
int mph_port(void);                            /* the port the application listens on */
const char *mph_bound_address(void);           /* and the address */
/* One interpolation cycle: wakes the clock task and waits until it is back at mpClkAnnounce. Returns 0,
 * or 1 when the cycle's work did not finish within timeout_us (an overrun: counted, not waited for). */
int mph_tick(uint32_t timeout_us);
/* The increments mpExRcsIncrementMove accepted since the last call, summed. */
void mph_take_increment(int32_t out[6]);
uint32_t mph_overruns(void);
const char *mph_last_alarm(void);
/* The fuzzer's clock: from now on mpGetRtc reads a time that moves only by mph_advance_ms (no tasks run). */
void mph_virtual_clock(uint32_t start_ms);
void mph_advance_ms(uint32_t ms);
void mph_stop(void);                           /* ends both tasks and closes every socket */

#endif
