/*
 * A stand-in for Force Dimension's libdhd, for tests and benchmarks of the omega7 driver without hardware.
 *
 * It exports the vendor's function names with the vendor's C signatures (dhd.h, "char ID = -1" selects the default
 * device), so the ctypes binding in plugins/devices/dhd.py runs exactly the code path it runs against the real
 * library. Return codes as the SDK documents them: 0 ok, 1 DHD_TIMEGUARD, 2 DHD_MOTOR_SATURATED, -1 error (the
 * reason in dhdErrorGetLast / dhdErrorGetLastStr).
 *
 * Internal device model (deliberately simple and deterministic):
 *  - gripper: a first-order spring towards a rest gap, gap = rest + sign * fg / GRIP_K with time constant GRIP_TAU,
 *    integrated on real elapsed time; a left-handed unit (system type 37, omega.7; 105, sigma.7) reports a negative
 *    gripper angle and linear velocity, and its gripper force acts in the opposite direction (the driver must undo
 *    that).
 *  - handle: quasi-static spring towards a rest position, p = rest + F / HANDLE_K, first-order lag.
 *  - force is produced only in FORCE mode, which dhdEnableForce(DHD_ON) enters (the brakes released); as on the real
 *    device, dhdSetBrakes leaves it whatever its argument: DHD_ON to BRAKE mode, DHD_OFF to IDLE mode, where no
 *    current reaches the motors (Force Dimension's API: "if the brakes are disabled, the device is forced into IDLE
 *    mode"), so a driver must release the brakes before it enables forces, not after. The SDK-side limits
 *    (dhdSetMaxForce, dhdSetMaxGripperForce) clamp what is applied.
 *  - the firmware watchdog (dhdSetWatchdog, SDK 3.3.2 and newer): a duration in units of 125 us, 0 = off. While
 *    forces are enabled, a force command (dhdSetForceAndGripperForce that reached the device, i.e. not skipped by
 *    the time guard) must arrive within that duration, else the "firmware" disables forces (as dhdEnableForce(0),
 *    force-off cause DHD_FORCEOFF_WATCHDOG). Evaluated lazily on the monotonic clock, at every vendor call and
 *    every test query, so it also acts while a call hangs. A test may take the firmware's clock in hand
 *    (standin_freeze_clock): from then on it moves only by standin_advance_clock(), so a step that comes late on a
 *    loaded machine trips nothing, and a test of the watchdog decides exactly when its duration has passed. The
 *    models above keep running on the monotonic clock.
 *
 * Test controls (not part of the vendor API) start with standin_.
 * Build: gcc -shared -fPIC -O2 -o libdhd.so dhd_standin.c -lm
 * Build with -DSTANDIN_NO_WATCHDOG for a library as an SDK older than 3.3.2 (no dhdSetWatchdog/dhdGetWatchdog; it
 * reports SDK 3.3.1).
 */
#include <math.h>
#include <stdbool.h>
#include <stdio.h>
#include <string.h>
#include <time.h>

#define DHD_TIMEGUARD 1
#define DHD_MOTOR_SATURATED 2

/* error codes, numbered as in the SDK's dhdc.h */
#define DHD_NO_ERROR 0
#define DHD_ERROR 1
#define DHD_ERROR_COM 2
#define DHD_ERROR_NO_DEVICE_FOUND 5
#define DHD_ERROR_NOT_AVAILABLE 6
#define DHD_ERROR_EXPERT_MODE_DISABLED 9
#define DHD_ERROR_DEVICE_NOT_READY 12
#define DHD_ERROR_INVALID_INDEX 15

/* causes for the device's FORCE OFF state (dhdc.h) */
#define DHD_FORCEOFF_NONE 0
#define DHD_FORCEOFF_BUTTON 1
#define DHD_FORCEOFF_WATCHDOG 3
#define DHD_FORCEOFF_SOFTWARE 4

#define WATCHDOG_UNIT 125e-6 /* s */

#define GRIP_K 400.0 /* N/m */
#define GRIP_TAU 0.005 /* s */
#define HANDLE_K 500.0 /* N/m */
#define HANDLE_TAU 0.01 /* s */

static struct {
    int present;        /* a device is plugged in (dhdOpen finds it) */
    int connected;      /* 0 after standin_unplug(): every call fails with DHD_ERROR_COM */
    int open;
    int serial;
    int system_type;    /* 35 omega.7 right, 37 omega.7 left, 104 sigma.7 right, 105 sigma.7 left (dhdc.h) */
    int force_enabled;
    int force_on_refused;
    int brakes;
    int gravity;
    int timeguard_every; /* every Nth force write returns DHD_TIMEGUARD (0: never) */
    long writes;
    long calls;
    double max_force, max_gripper_force;
    double f[3], fg;    /* as commanded */
    double fa[3], fga;  /* as applied */
    double rest_gap, gap, gap_vel;
    double rest[3], pos[3];
    int buttons[4];
    double com_freq;    /* kHz */
    double t_last;
    int last_error;
    char last_str[128];
    unsigned char watchdog; /* firmware watchdog, units of 125 us (0: off) */
    int watchdog_fails;     /* test switch: dhdSetWatchdog answers -1 */
    int write_fails;        /* test switch: dhdSetForceAndGripperForce answers -1 (nothing reaches the device) */
    int force_off_fails;    /* test switch: dhdEnableForce(0) answers -1 (forces stay as they are) */
    double t_cmd;           /* when the device last received a force command (or the watchdog was set) */
    long watchdog_trips;
    int force_off_cause;
    int expert;             /* dhdEnableExpertMode: the expert SDK calls (dhdSetWatchdog, ...) need it */
    double peak;            /* largest |component| of a force command received since standin_mark() */
    int clock_frozen;       /* the firmware's clock moves only by standin_advance_clock() */
    double clock_t;         /* its time then (s, on the monotonic clock's scale) */
} S;

/* test control: vendor calls that block ("hang") until released; outside S (read by other threads) */
static char hang_name[64];
static int hang_armed;
static int hanging;

static double now_s(void) {
    struct timespec ts;
    clock_gettime(CLOCK_MONOTONIC, &ts);
    return ts.tv_sec + ts.tv_nsec * 1e-9;
}

/* the firmware's clock: the watchdog's time base */
static double fw_now(void) { return S.clock_frozen ? S.clock_t : now_s(); }

static int fail(int code, const char *msg) {
    S.last_error = code;
    snprintf(S.last_str, sizeof S.last_str, "%s", msg);
    return -1;
}

static int ok(void) {
    S.last_error = DHD_NO_ERROR;
    return 0;
}

static double hand_sign(void) { return S.system_type == 37 || S.system_type == 105 ? -1.0 : 1.0; }

static void apply_forces(void);

/* the device firmware's watchdog: forces off when no force command came within the duration */
static void firmware(void) {
    if (S.watchdog && S.force_enabled && S.connected && fw_now() - S.t_cmd > S.watchdog * WATCHDOG_UNIT) {
        S.force_enabled = 0;
        S.force_off_cause = DHD_FORCEOFF_WATCHDOG;
        S.fg = 0; S.f[0] = S.f[1] = S.f[2] = 0;
        S.watchdog_trips++;
        apply_forces();
    }
}

/* blocks while a hang is armed for this call (test control) */
static void hang_point(const char *name) {
    if (!__atomic_load_n(&hang_armed, __ATOMIC_ACQUIRE) || strcmp(name, hang_name) != 0) return;
    __atomic_add_fetch(&hanging, 1, __ATOMIC_ACQ_REL);
    struct timespec ts = {0, 100000}; /* 100 us */
    while (__atomic_load_n(&hang_armed, __ATOMIC_ACQUIRE)) nanosleep(&ts, NULL);
    __atomic_sub_fetch(&hanging, 1, __ATOMIC_ACQ_REL);
}

/* checks done by every device call */
static int check(char ID) {
    S.calls++;
    if (!S.connected) return fail(DHD_ERROR_COM, "communication error between the host and the haptic device");
    if (!S.open) return fail(DHD_ERROR_DEVICE_NOT_READY, "device not open");
    if (ID != -1 && ID != 0) return fail(DHD_ERROR_INVALID_INDEX, "invalid device ID");
    firmware();
    return 0;
}

static void apply_forces(void) {
    int on = S.force_enabled;
    double n = sqrt(S.f[0] * S.f[0] + S.f[1] * S.f[1] + S.f[2] * S.f[2]);
    double k = (on && n > S.max_force && n > 0) ? S.max_force / n : 1.0;
    for (int i = 0; i < 3; i++) S.fa[i] = on ? S.f[i] * k : 0.0;
    double g = S.fg;
    if (g > S.max_gripper_force) g = S.max_gripper_force;
    if (g < -S.max_gripper_force) g = -S.max_gripper_force;
    S.fga = on ? g : 0.0;
}

/* advance the model to the current time */
static void advance(void) {
    double t = now_s();
    double dt = t - S.t_last;
    S.t_last = t;
    if (dt <= 0) return;
    if (dt > 0.05) dt = 0.05;
    double target = S.rest_gap + hand_sign() * S.fga / GRIP_K; /* fga along the SDK axis */
    if (target < 0) target = 0;
    if (target > 0.025) target = 0.025;
    double a = 1.0 - exp(-dt / GRIP_TAU);
    S.gap += (target - S.gap) * a;
    S.gap_vel = (target - S.gap) / GRIP_TAU; /* the first-order model's derivative */
    double b = 1.0 - exp(-dt / HANDLE_TAU);
    for (int i = 0; i < 3; i++) S.pos[i] += (S.rest[i] + S.fa[i] / HANDLE_K - S.pos[i]) * b;
}

/* ------------------------------------------------------------------------------------------- test controls */
void standin_reset(void) {
    __atomic_store_n(&hang_armed, 0, __ATOMIC_RELEASE);
    memset(&S, 0, sizeof S);
    S.present = 1;
    S.connected = 1;
    S.serial = 12345;
    S.system_type = 35;
    S.brakes = 1;
    S.max_force = 12.0;
    S.max_gripper_force = 8.0;
    S.rest_gap = 0.015;
    S.gap = 0.015;
    S.com_freq = 4.0;
    S.t_last = now_s();
    snprintf(S.last_str, sizeof S.last_str, "no error");
}
void standin_set_present(int v) { S.present = v; }
void standin_unplug(void) { S.connected = 0; }
void standin_replug(void) { S.connected = 1; }
void standin_set_system_type(int t) { S.system_type = t; }
void standin_set_timeguard_every(int n) { S.timeguard_every = n; }
void standin_set_rest(double gap, double x, double y, double z) {
    S.rest_gap = gap; S.gap = gap;
    S.rest[0] = x; S.rest[1] = y; S.rest[2] = z;
    S.pos[0] = x; S.pos[1] = y; S.pos[2] = z;
}
void standin_set_button(int index, int value) { if (index >= 0 && index < 4) S.buttons[index] = value; }
void standin_set_com_freq(double khz) { S.com_freq = khz; }
/* out: fx fy fz fg as applied, then as commanded (the firmware watchdog evaluated first) */
void standin_get_forces(double *applied4, double *commanded4) {
    firmware();
    for (int i = 0; i < 3; i++) { applied4[i] = S.fa[i]; commanded4[i] = S.f[i]; }
    applied4[3] = S.fga; commanded4[3] = S.fg;
}
/* out: open, force_enabled, brakes, gravity (the firmware watchdog evaluated first) */
void standin_get_flags(int *flags4) {
    firmware();
    flags4[0] = S.open; flags4[1] = S.force_enabled; flags4[2] = S.brakes; flags4[3] = S.gravity;
}
/* the firmware watchdog as set (units of 125 us, 0 off; kept after dhdClose), and how often it cut forces */
int standin_get_watchdog(void) { return S.watchdog; }
long standin_get_watchdog_trips(void) { firmware(); return S.watchdog_trips; }
int standin_get_force_off_cause(void) { firmware(); return S.force_off_cause; }
void standin_set_watchdog_fails(int v) { S.watchdog_fails = v; }
void standin_set_write_fails(int v) { S.write_fails = v; }
void standin_set_force_off_fails(int v) { S.force_off_fails = v; }
/* the largest |component| of the force commands received since this call */
void standin_mark(void) { S.peak = 0.0; }
/* the operator presses the device's force button: forces off, cause BUTTON (as the real device does) */
void standin_press_force_button(void) {
    S.force_enabled = 0;
    S.force_off_cause = DHD_FORCEOFF_BUTTON;
    S.fg = 0; S.f[0] = S.f[1] = S.f[2] = 0;
    apply_forces();
}
/* forces do not come on at dhdEnableForce(DHD_ON) (which returns ok), off by this cause (0: they come on) */
void standin_set_force_on_refused(int cause) { S.force_on_refused = cause; }
int standin_get_expert(void) { return S.expert; }
/* the firmware's clock stops here (until standin_reset); standin_advance_clock(dt) moves it on by dt seconds, the
   watchdog evaluated at the new time */
void standin_freeze_clock(void) {
    if (!S.clock_frozen) { S.clock_t = now_s(); S.clock_frozen = 1; }
}
void standin_advance_clock(double dt) {
    if (S.clock_frozen && dt > 0) S.clock_t += dt;
    firmware();
}
double standin_get_peak(void) { return S.peak; }
/* every later call of the named vendor function (dhdGetPosition) blocks until standin_release(); standin_hanging()
   counts the calls blocked now */
void standin_hang(const char *name) {
    snprintf(hang_name, sizeof hang_name, "%s", name);
    __atomic_store_n(&hang_armed, 1, __ATOMIC_RELEASE);
}
void standin_release(void) { __atomic_store_n(&hang_armed, 0, __ATOMIC_RELEASE); }
int standin_hanging(void) { return __atomic_load_n(&hanging, __ATOMIC_ACQUIRE); }
void standin_get_limits(double *lim2) { lim2[0] = S.max_force; lim2[1] = S.max_gripper_force; }
long standin_get_writes(void) { return S.writes; }
long standin_get_calls(void) { return S.calls; }

__attribute__((constructor)) static void init(void) { standin_reset(); }

/* ------------------------------------------------------------------------------------------- vendor API */
void dhdGetSDKVersion(int *major, int *minor, int *release, int *revision) {
#ifdef STANDIN_NO_WATCHDOG
    *major = 3; *minor = 3; *release = 1; *revision = 0;    /* before dhdSetWatchdog (3.3.2) */
#else
    *major = 3; *minor = 17; *release = 0; *revision = 0;   /* "3.17.0-standin" */
#endif
}
int dhdErrorGetLast(void) { return S.last_error; }
const char *dhdErrorGetLastStr(void) { return S.last_str; }
const char *dhdErrorGetStr(int error) {
    switch (error) {
    case DHD_NO_ERROR: return "no error";
    case DHD_ERROR_COM: return "communication error between the host and the haptic device";
    case DHD_ERROR_NO_DEVICE_FOUND: return "no compatible Force Dimension device found";
    case DHD_ERROR_DEVICE_NOT_READY: return "device not open";
    default: return "undocumented error";
    }
}
int dhdGetDeviceCount(void) { return S.connected && S.present ? 1 : 0; }

static int do_open(void) {
    if (!S.present || !S.connected) return fail(DHD_ERROR_NO_DEVICE_FOUND, "no compatible Force Dimension device found");
    S.open = 1;
    S.force_enabled = 0;
    S.brakes = 1;
    S.t_last = now_s();
    ok();
    return 0; /* device ID */
}
int dhdOpen(void) { return do_open(); }
int dhdOpenID(char index) {
    if (index != 0) return fail(DHD_ERROR_NO_DEVICE_FOUND, "no compatible Force Dimension device found at that index");
    return do_open();
}
int dhdOpenSerial(int serial) {
    if (serial != S.serial) return fail(DHD_ERROR_NO_DEVICE_FOUND, "no device with that serial number");
    return do_open();
}
int dhdClose(char ID) {
    if (!S.open) return fail(DHD_ERROR_DEVICE_NOT_READY, "device not open");
    S.open = 0;
    S.force_enabled = 0;
    S.fg = 0; S.f[0] = S.f[1] = S.f[2] = 0;
    apply_forces();
    return ok();
}
int dhdGetDeviceID(void) { return S.open ? 0 : -1; }
int dhdGetSystemType(char ID) {
    if (check(ID)) return -1;
    ok();
    return S.system_type;
}
int dhdGetSerialNumber(unsigned short *sn, char ID) {
    if (check(ID)) return -1;
    *sn = (unsigned short)S.serial;
    return ok();
}
bool dhdIsLeftHanded(char ID) {
    if (check(ID)) return false;
    ok();
    return hand_sign() < 0;
}
int dhdEnableForce(unsigned char val, char ID) {
    if (check(ID)) return -1;
    if (!val && S.force_off_fails) return fail(DHD_ERROR, "error");
    S.force_enabled = val ? 1 : 0;
    S.force_off_cause = val ? DHD_FORCEOFF_NONE : DHD_FORCEOFF_SOFTWARE;
    if (val) S.brakes = 0; /* FORCE mode: the brakes released */
    if (val && S.force_on_refused) { S.force_enabled = 0; S.force_off_cause = S.force_on_refused; }
    if (!val) { S.fg = 0; S.f[0] = S.f[1] = S.f[2] = 0; }
    apply_forces();
    return ok();
}
int dhdSetBrakes(int val, char ID) {
    if (check(ID)) return -1;
    S.brakes = val ? 1 : 0;
    if (S.force_enabled) { /* out of FORCE mode: BRAKE (val) or IDLE (!val), forces off either way */
        S.force_enabled = 0;
        S.force_off_cause = DHD_FORCEOFF_SOFTWARE;
        S.fg = 0; S.f[0] = S.f[1] = S.f[2] = 0;
    }
    apply_forces();
    return ok();
}
int dhdSetGravityCompensation(int val, char ID) {
    if (check(ID)) return -1;
    S.gravity = val ? 1 : 0;
    return ok();
}
#ifndef STANDIN_NO_MAX_FORCE   /* -DSTANDIN_NO_MAX_FORCE: a library as SDK 3.7.0's dhdc.h, without these two */
int dhdSetMaxForce(double f, char ID) {
    if (check(ID)) return -1;
    S.max_force = f < 0 ? 12.0 : f; /* a negative value removes the limit */
    return ok();
}
double dhdGetMaxForce(char ID) {
    if (check(ID)) return -1.0;
    ok();
    return S.max_force;
}
int dhdSetMaxGripperForce(double f, char ID) {
    if (check(ID)) return -1;
    S.max_gripper_force = f < 0 ? 8.0 : f;
    return ok();
}
#endif
int dhdGetPosition(double *px, double *py, double *pz, char ID) {
    if (check(ID)) return -1;
    hang_point("dhdGetPosition");
    advance();
    *px = S.pos[0]; *py = S.pos[1]; *pz = S.pos[2];
    return ok();
}
int dhdGetLinearVelocity(double *vx, double *vy, double *vz, char ID) {
    if (check(ID)) return -1;
    *vx = *vy = *vz = 0.0;
    return ok();
}
int dhdGetGripperGap(double *g, char ID) {
    if (check(ID)) return -1;
    advance();
    *g = S.gap;
    return ok();
}
int dhdGetGripperAngleRad(double *a, char ID) {
    if (check(ID)) return -1;
    advance();
    *a = hand_sign() * S.gap / 0.05; /* small-angle model: 50 mm finger radius */
    return ok();
}
int dhdGetGripperLinearVelocity(double *vg, char ID) {
    if (check(ID)) return -1;
    advance();
    *vg = hand_sign() * S.gap_vel;
    return ok();
}
int dhdSetForceAndGripperForce(double fx, double fy, double fz, double fg, char ID) {
    if (check(ID)) return -1;
    advance();
    if (S.write_fails) return fail(DHD_ERROR, "error");
    S.writes++;
    ok();
    /* the time guard: the call came too soon after the previous one, and the command is not sent (skipped) */
    if (S.force_enabled && S.timeguard_every > 0 && S.writes % S.timeguard_every == 0) return DHD_TIMEGUARD;
    S.t_cmd = fw_now(); /* received: feeds the firmware watchdog */
    double m = fabs(fg);
    if (fabs(fx) > m) m = fabs(fx);
    if (fabs(fy) > m) m = fabs(fy);
    if (fabs(fz) > m) m = fabs(fz);
    if (m > S.peak) S.peak = m;
    S.f[0] = fx; S.f[1] = fy; S.f[2] = fz;
    S.fg = fg; /* in the SDK's gripper axis, which follows the (mirrored) angle on a left unit */
    apply_forces();
    if (!S.force_enabled) return 0;
    double n = sqrt(fx * fx + fy * fy + fz * fz);
    if (n > S.max_force || fabs(fg) > S.max_gripper_force) return DHD_MOTOR_SATURATED;
    return 0;
}
int dhdGetButton(int index, char ID) {
    if (check(ID)) return -1;
    if (index < 0 || index >= 4) return fail(DHD_ERROR_INVALID_INDEX, "invalid button index");
    ok();
    return S.buttons[index];
}
double dhdGetComFreq(char ID) {
    if (check(ID)) return 0.0;
    ok();
    return S.com_freq;
}
int dhdStop(char ID) {
    if (check(ID)) return -1;
    S.force_enabled = 0;
    S.brakes = 1;
    S.fg = 0; S.f[0] = S.f[1] = S.f[2] = 0;
    apply_forces();
    return ok();
}

/* status[DHD_MAX_STATUS]: DHD_STATUS_POWER 0, CONNECTED 1, FORCE 5, BRAKE 6, FORCEOFFCAUSE 14 (the others read 0
   here); DHD_MAX_STATUS is 17 (DHD_STATUS_AXISCHECKED 16) in the SDK this stand-in reports (dhdc.h of SDK 3.11 has
   17), 16 in older ones: the SDK writes that many, whatever the caller's buffer */
#ifdef STANDIN_NO_WATCHDOG
#define DHD_MAX_STATUS 16
#else
#define DHD_MAX_STATUS 17
#endif
int dhdGetStatus(int status[DHD_MAX_STATUS], char ID) {
    if (check(ID)) return -1;
    for (int i = 0; i < DHD_MAX_STATUS; i++) status[i] = 0;
    status[0] = 1;
    status[1] = S.connected;
    status[5] = S.force_enabled;
    status[6] = S.brakes;
    status[14] = S.force_off_cause;
    return ok();
}
int dhdEnableExpertMode(void) { S.expert = 1; return ok(); }
int dhdDisableExpertMode(void) { S.expert = 0; return ok(); }

#ifndef STANDIN_NO_WATCHDOG
/* added in release 3.3.2, declared among the expert SDK's calls: the stand-in asks for expert mode */
int dhdSetWatchdog(unsigned char val, char ID) {
    if (check(ID)) return -1;
    if (!S.expert) return fail(DHD_ERROR_EXPERT_MODE_DISABLED, "expert mode disabled");
    if (S.watchdog_fails) return fail(DHD_ERROR_NOT_AVAILABLE, "feature not available on this device");
    S.watchdog = val;
    S.t_cmd = fw_now();
    return ok();
}
int dhdGetWatchdog(unsigned char *val, char ID) {
    if (check(ID)) return -1;
    if (!S.expert) return fail(DHD_ERROR_EXPERT_MODE_DISABLED, "expert mode disabled");
    *val = S.watchdog;
    return ok();
}
#endif
