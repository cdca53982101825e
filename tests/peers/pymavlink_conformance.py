#!/usr/bin/env python3
"""pymavlink conformance flight: an independent MAVLink implementation (pymavlink 2.4.49) drives a
vehicle through the calls a ground station or companion computer makes, and prints one line per
call: CALL <name> OK|FAIL <detail>, then SUMMARY failed=...

usage: pymavlink_conformance.py CONNECT --flavour px4|ardupilot [--strict] [--time-scale K]
  CONNECT: a pymavlink connection string, e.g. udpin:127.0.0.1:14550 (the vehicle sends there)

The same script runs against the mock PX4, the mock ArduPilot (skyherd-sitl autopilot) and a
real ArduCopter SITL; where the two families differ (takeoff, offboard/guided, refusal codes)
it asks each the way its own documentation says. Exit 2 with --strict when any call failed.
"""
import argparse
import math
import os
import sys
import time

os.environ.setdefault("MAVLINK20", "1")
from pymavlink import mavutil  # noqa: E402

M = mavutil.mavlink
FAILED = []
T0 = time.monotonic()


def out(line):
    print("[%6.1fs] %s" % (time.monotonic() - T0, line), flush=True)


def report(name, ok, detail=""):
    out("CALL %s %s %s" % (name, "OK" if ok else "FAIL", detail))
    if not ok:
        FAILED.append(name)
    return ok


class Vehicle:
    def __init__(self, connect, scale):
        self.link = mavutil.mavlink_connection(connect, source_system=245, source_component=190)
        self.scale = scale
        self.sysid = None
        self.armed = False
        self.mode = None
        self.position = None
        self.texts = []

    def recv(self, types, timeout, cond=None):
        """The next message of `types` (from the vehicle) meeting cond, or None."""
        end = time.monotonic() + timeout * self.scale
        while time.monotonic() < end:
            msg = self.link.recv_match(blocking=True, timeout=0.05)
            if msg is None:
                continue
            self.note(msg)
            if msg.get_type() in types and (cond is None or cond(msg)):
                return msg
        return None

    def note(self, msg):
        t = msg.get_type()
        if t == "HEARTBEAT" and msg.get_srcComponent() == 1 and msg.autopilot != M.MAV_AUTOPILOT_INVALID:
            self.armed = bool(msg.base_mode & M.MAV_MODE_FLAG_SAFETY_ARMED)
            self.mode = msg.custom_mode
        elif t == "LOCAL_POSITION_NED":
            self.position = (msg.x, msg.y, msg.z)
        elif t == "STATUSTEXT":
            self.texts.append(msg.text)

    def command(self, cmd, params, timeout=3.0):
        """COMMAND_LONG; the ACK for it (or None)."""
        p = list(params) + [0.0] * (7 - len(params))
        self.link.mav.command_long_send(self.sysid, 1, cmd, 0, *p)
        return self.recv({"COMMAND_ACK"}, timeout, lambda m: m.command == cmd)

    def pump(self, seconds):
        self.recv(set(), seconds)

    def wait(self, pred, timeout):
        end = time.monotonic() + timeout * self.scale
        while time.monotonic() < end:
            self.recv(set(), 0.05)
            if pred():
                return True
        return False


def ack_text(ack):
    if ack is None:
        return "no ACK"
    targets = ""
    if hasattr(ack, "target_system"):
        targets = " to %d/%d" % (ack.target_system, ack.target_component)
    return "result %d%s" % (ack.result, targets)


def run(v, flavour):
    hb = v.link.wait_heartbeat(timeout=30 * v.scale)
    if not report("wait_heartbeat", hb is not None,
                  "" if hb is None else "system %d autopilot %d type %d" % (
                      hb.get_srcSystem(), hb.autopilot, hb.type)):
        return
    v.sysid = hb.get_srcSystem()
    v.link.target_system, v.link.target_component = v.sysid, 1
    v.note(hb)

    ack = v.command(M.MAV_CMD_REQUEST_MESSAGE, [M.MAVLINK_MSG_ID_AUTOPILOT_VERSION])
    version = v.recv({"AUTOPILOT_VERSION"}, 3)
    report("command_long REQUEST_MESSAGE(AUTOPILOT_VERSION)", ack is not None and ack.result == 0 and version,
           "%s, flight_sw_version %s" % (ack_text(ack), hex(version.flight_sw_version) if version else None))
    ack = v.command(M.MAV_CMD_REQUEST_MESSAGE, [M.MAVLINK_MSG_ID_HOME_POSITION])
    home = v.recv({"HOME_POSITION"}, 5)
    report("command_long REQUEST_MESSAGE(HOME_POSITION)", home is not None,
           "%s, %s" % (ack_text(ack), "lat %d" % home.latitude if home else "none"))

    # Parameters: the whole list, then one set that the vehicle must echo.
    v.link.param_fetch_all()
    first = v.recv({"PARAM_VALUE"}, 10)
    total = first.param_count if first else 0
    seen = {first.param_index} if first else set()
    while first and len(seen) < total:
        m = v.recv({"PARAM_VALUE"}, 5)
        if m is None:
            break
        seen.add(m.param_index)
    report("param_fetch_all", total > 0 and len(seen) == total, "%d of %d" % (len(seen), total))
    name, value = ("COM_OF_LOSS_T", 1.5) if flavour == "px4" else ("DISARM_DELAY", 10.0)
    v.link.param_set_send(name, value,
                          M.MAV_PARAM_TYPE_REAL32 if flavour == "px4" else M.MAV_PARAM_TYPE_INT16)
    echo = v.recv({"PARAM_VALUE"}, 5, lambda m: m.param_id == name)
    report("param_set_send(%s=%g)" % (name, value), echo is not None and abs(echo.param_value - value) < 1e-6,
           "echo %s" % (echo.param_value if echo else None))

    v.link.mav.mission_request_list_send(v.sysid, 1)
    count = v.recv({"MISSION_COUNT"}, 5)
    report("mission_request_list_send", count is not None, "count %s" % (count.count if count else None))

    v.link.mav.timesync_send(0, int(time.time() * 1e9))
    sync = v.recv({"TIMESYNC"}, 5, lambda m: m.tc1 != 0)
    report("timesync_send", sync is not None, "tc1 %s" % (sync.tc1 if sync else None))

    ack = v.command(M.MAV_CMD_SET_MESSAGE_INTERVAL, [M.MAVLINK_MSG_ID_LOCAL_POSITION_NED, 100000])
    pos = v.recv({"LOCAL_POSITION_NED"}, 90)  # a real ArduCopter's EKF needs ~42 s (sim)
    report("command_long SET_MESSAGE_INTERVAL(LOCAL_POSITION_NED, 10 Hz)", pos is not None, ack_text(ack))
    ack = v.command(M.MAV_CMD_SET_MESSAGE_INTERVAL, [M.MAVLINK_MSG_ID_EXTENDED_SYS_STATE, 1000000])
    state = v.recv({"EXTENDED_SYS_STATE"}, 5)
    report("command_long SET_MESSAGE_INTERVAL(EXTENDED_SYS_STATE, 1 Hz)", state is not None,
           "%s, landed_state %s" % (ack_text(ack), state.landed_state if state else None))

    if flavour == "ardupilot":
        # mavutil's set_mode for ArduPilot: the SET_MODE message; GUIDED before arming.
        v.link.set_mode(4)
        ok = v.wait(lambda: v.mode == 4, 5)
        report("set_mode(GUIDED) [SET_MODE message]", ok, "custom_mode %s" % v.mode)

    # Arm (a real ArduCopter refuses until its pre-arm checks pass: retried).
    end = time.monotonic() + 90 * v.scale
    ack = None
    while time.monotonic() < end:
        ack = v.command(M.MAV_CMD_COMPONENT_ARM_DISARM, [1])
        if ack is not None and ack.result == 0:
            break
        v.pump(1)
    report("command_long COMPONENT_ARM_DISARM(arm)", ack is not None and ack.result == 0 and
           v.wait(lambda: v.armed, 5), ack_text(ack))

    # Takeoff: PX4's param 7 is AMSL (NaN: MIS_TAKEOFF_ALT), ArduCopter's is above home.
    alt = float("nan") if flavour == "px4" else 2.0
    ack = v.command(M.MAV_CMD_NAV_TAKEOFF, [0, 0, 0, float("nan"), float("nan"), float("nan"), alt])
    up = v.wait(lambda: v.position is not None and -v.position[2] >= 1.5, 30)
    report("command_long NAV_TAKEOFF", ack is not None and ack.result == 0 and up,
           "%s, height %.2f m" % (ack_text(ack), -v.position[2] if v.position else float("nan")))

    # Disarming in the air is refused (unless forced).
    ack = v.command(M.MAV_CMD_COMPONENT_ARM_DISARM, [0])
    report("command_long COMPONENT_ARM_DISARM(disarm in the air) refused",
           ack is not None and ack.result != 0 and v.armed, ack_text(ack))

    # External control: PX4 OFFBOARD needs a live stream; ArduCopter is in GUIDED already.
    def setpoint(vx, vy, mask):
        v.link.mav.set_position_target_local_ned_send(
            0, v.sysid, 1, M.MAV_FRAME_LOCAL_NED, mask, 0, 0, 0, vx, vy, 0, 0, 0, 0, 0, 0)

    if flavour == "px4":
        for _ in range(5):
            setpoint(0, 0, 0x0DC7)
            v.pump(0.05)
        ack = v.command(M.MAV_CMD_DO_SET_MODE, [M.MAV_MODE_FLAG_CUSTOM_MODE_ENABLED, 6, 0])
        report("command_long DO_SET_MODE(OFFBOARD)", ack is not None and ack.result == 0, ack_text(ack))
    for mask, (vx, vy), label in [(0x0DC7, (1.0, 0.0), "velocity 0x0DC7 north"),
                                  (0x09C7, (0.0, 1.0), "velocity+yaw 0x09C7 east")]:
        start = v.position
        end = time.monotonic() + 2.0 * v.scale
        while time.monotonic() < end:
            setpoint(vx, vy, mask)
            v.pump(0.05)
        moved = (v.position[0] - start[0], v.position[1] - start[1]) if start and v.position else (0, 0)
        along = moved[0] * vx + moved[1] * vy
        report("set_position_target_local_ned_send(%s)" % label, along > 0.5,
               "moved %.2f m north, %.2f m east" % moved)

    ack = v.command(M.MAV_CMD_NAV_LAND, [0, 0, 0, float("nan"), float("nan"), float("nan"), float("nan")])
    down = v.wait(lambda: not v.armed, 60)
    report("command_long NAV_LAND (lands, disarms)", ack is not None and ack.result == 0 and down, ack_text(ack))

    # COMMAND_INT is served like COMMAND_LONG.
    v.link.mav.command_int_send(v.sysid, 1, M.MAV_FRAME_GLOBAL, M.MAV_CMD_REQUEST_MESSAGE, 0, 0,
                                M.MAVLINK_MSG_ID_AUTOPILOT_VERSION, 0, 0, 0, 0, 0, 0)
    ack = v.recv({"COMMAND_ACK"}, 3, lambda m: m.command == M.MAV_CMD_REQUEST_MESSAGE)
    report("command_int_send REQUEST_MESSAGE", ack is not None and ack.result == 0, ack_text(ack))
    # A command nobody implements: acknowledged UNSUPPORTED.
    ack = v.command(M.MAV_CMD_PAYLOAD_PREPARE_DEPLOY, [0])
    report("command_long PAYLOAD_PREPARE_DEPLOY (unknown) UNSUPPORTED",
           ack is not None and ack.result == M.MAV_RESULT_UNSUPPORTED, ack_text(ack))
    report("statustext on refusals", len(v.texts) > 0, "%d texts, e.g. %r" % (len(v.texts), v.texts[-1] if v.texts else None))


def main():
    ap = argparse.ArgumentParser()
    ap.add_argument("connect")
    ap.add_argument("--flavour", choices=["px4", "ardupilot"], required=True)
    ap.add_argument("--strict", action="store_true")
    ap.add_argument("--time-scale", type=float, default=1.0)
    args = ap.parse_args()
    v = Vehicle(args.connect, args.time_scale)
    try:
        run(v, args.flavour)
    except Exception as e:  # a broken step is a failed call, not a traceback
        report("exception", False, "%s: %s" % (type(e).__name__, e))
    out("SUMMARY failed=%s" % (",".join(FAILED) or "none"))
    return 2 if (args.strict and FAILED) else 0


if __name__ == "__main__":
    sys.exit(main())
