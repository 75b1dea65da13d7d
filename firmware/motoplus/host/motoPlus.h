/*
 * The part of the MotoPlus API that mpcl_app.c uses, declared for a host build.
 *
 * On the controller the application includes Yaskawa's motoPlus.h from the SDK instead; this header
 * carries only the names, types and signatures of the calls the application makes (as the public
 * MotoPlus sources of MotoROS / motoman_driver use them), so that the same application source compiles
 * on a PC against mp_host.c, whose motion calls drive sim_cell's simulated arm. Widths follow the
 * controller's 32-bit ABI: LONG is 32 bits here too.
 */
#ifndef MOTOPLUS_HOST_H
#define MOTOPLUS_HOST_H

#include <stdint.h>
#include <sys/select.h>
#include <sys/socket.h>
#include <sys/time.h>
#include <netinet/in.h>
#include <netinet/tcp.h>

typedef int32_t LONG;
typedef uint32_t ULONG;
typedef int16_t SHORT;
typedef uint16_t USHORT;
typedef uint8_t UCHAR;
typedef int STATUS;
typedef int BOOL;
typedef ULONG CTRLG_T;
typedef int SEM_ID;
typedef void (*FUNCPTR)(int, int, int, int, int, int, int, int, int, int);

#define OK 0
#define ERROR (-1)
#define TRUE 1
#define FALSE 0
#define WAIT_FOREVER (-1)
#define NO_WAIT 0

/* ---------------------------------------------------------------- tasks, clocks, semaphores */
#define MP_INTERPOLATION_CLK 1
#define MP_PRI_IP_CLK_TAKE 1      /* the priority of a task that runs on the interpolation clock */
#define MP_PRI_TIME_NORMAL 6      /* an ordinary task: sockets */
#define MP_STACK_SIZE (64 * 1024)
#define SEM_Q_FIFO 0
#define SEM_EMPTY 0
#define SEM_FULL 1

int mpCreateTask(int priority, int stackSize, FUNCPTR entryPt, int arg1, int arg2, int arg3, int arg4, int arg5,
                 int arg6, int arg7, int arg8, int arg9, int arg10);
STATUS mpClkAnnounce(int clk_id);     /* blocks until the clock's next tick; negative when it will not come */
ULONG mpGetRtc(void);                 /* the controller's own millisecond clock, from power-on */
SEM_ID mpSemBCreate(int options, int initialState);
STATUS mpSemTake(SEM_ID semId, int timeout);
STATUS mpSemGive(SEM_ID semId);
#define mpExitUsrRoot return

/* ---------------------------------------------------------------- sockets (BSD calls, mp-prefixed) */
int mpSocket(int domain, int type, int protocol);
int mpBind(int s, struct sockaddr *name, int namelen);
int mpListen(int s, int backlog);
int mpAccept(int s, struct sockaddr *addr, int *addrlen);
int mpRecv(int s, char *buf, int bufLen, int flags);
int mpSend(int s, const char *buf, int bufLen, int flags);
int mpSelect(int width, fd_set *readFds, fd_set *writeFds, fd_set *exceptFds, struct timeval *timeout);
int mpSetsockopt(int s, int level, int optname, char *optval, int optlen);
STATUS mpClose(int fd);
USHORT mpHtons(USHORT hostshort);
ULONG mpHtonl(ULONG hostlong);
ULONG mpNtohl(ULONG netlong);

/* ---------------------------------------------------------------- variables, I/O, alarms */
#define MP_RESTYPE_VAR_D 3        /* the 32-bit integer variables D000.. */
typedef struct { USHORT usType; USHORT usIndex; } MP_VAR_INFO;
LONG mpGetVarData(MP_VAR_INFO *sData, LONG *rData, LONG num);

typedef struct { ULONG ulAddr; } MP_IO_INFO;
LONG mpReadIO(MP_IO_INFO *sData, USHORT *rData, LONG num);

int mpSetAlarm(SHORT alm_code, char *alm_msg, UCHAR sub_code);

/* ---------------------------------------------------------------- positions and increments */
/* Constants below are this header's own values; the SDK header has the controller's. */
#define MP_GRP_AXES_NUM 8
#define MP_GRP_NUM 32
#define MP_INC_PULSE_DTYPE 0x80
#define MP_INC_ANGLE_DTYPE 0x81
#define MP_INC_BF_DTYPE 0x90      /* Cartesian increment in the base frame */
#define MP_INC_RF_DTYPE 0x91      /* robot frame */
#define MP_INC_TF_DTYPE 0x92      /* tool frame */
#define MP_INC_UF_DTYPE 0x93      /* user frame */

typedef struct { USHORT sCtrlGrp; } MP_CTRL_GRP_SEND_DATA;
typedef struct { LONG lPos[MP_GRP_AXES_NUM]; USHORT sConfig; } MP_CART_POS_RSP_DATA;
LONG mpGetCartPos(MP_CTRL_GRP_SEND_DATA *sData, MP_CART_POS_RSP_DATA *rData);

typedef struct { UCHAR data[8]; CTRLG_T ei_ctrl_grp; } MP_POS_TAG;
typedef struct { MP_POS_TAG pos_tag; LONG pos[MP_GRP_AXES_NUM]; } MP_GRP_POS_INFO;
typedef struct {
    CTRLG_T ctrl_grp;
    CTRLG_T m_ctrl_grp;
    CTRLG_T s_ctrl_grp;
    MP_GRP_POS_INFO grp_pos_info[MP_GRP_NUM];
} MP_EXPOS_DATA;
int mpExRcsIncrementMove(MP_EXPOS_DATA *src_p);  /* this interpolation cycle's increment; 0 or an error */

#endif
