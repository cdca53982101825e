"""An independent MAVLink 2 peer (pymavlink) for skyherd's interop test.

Talks to one mock autopilot at --autopilot HOST:PORT (udpout): sees its HEARTBEAT and
LOCAL_POSITION_NED, arms it, streams velocity setpoints and switches it to PX4 OFFBOARD,
then reads the .tlog at --tlog. Prints one JSON object on stdout; exit status 0 only if
every step passed. Run with MAVLINK20=1.
"""

import argparse
import json
import os
import sys
import time

os.environ.setdefault("MAVLINK_DIALECT", "common")
from pymavlink import mavutil  # noqa: E402

VELOCITY_ONLY = 0x0DC7
OFFBOARD = 6 << 16


def fail(result, why):
    result["error"] = why
    print(json.dumps(result), flush=True)
    sys.exit(1)


def wait_for(conn, kind, timeout, predicate=lambda m: True, keepalive=None):
    deadline = time.time() + timeout
    next_keepalive = 0.0
    while time.time() < deadline:
        if keepalive is not None and time.time() >= next_keepalive:
            keepalive()
            next_keepalive = time.time() + 0.05
        msg = conn.recv_match(type=kind, blocking=True, timeout=0.05)
        if msg is not None and predicate(msg):
            return msg
    return None


def main():
    parser = argparse.ArgumentParser()
    parser.add_argument("--autopilot", required=True)
    parser.add_argument("--tlog", required=True)
    args = parser.parse_args()
    result = {"mavlink20": os.environ.get("MAVLINK20") == "1"}

    conn = mavutil.mavlink_connection("udpout:" + args.autopilot, source_system=254)

    def gcs_heartbeat():
        conn.mav.heartbeat_send(mavutil.mavlink.MAV_TYPE_GCS, mavutil.mavlink.MAV_AUTOPILOT_INVALID, 0, 0, 0)

    hb = wait_for(conn, "HEARTBEAT", 10, lambda m: m.type == mavutil.mavlink.MAV_TYPE_QUADROTOR, gcs_heartbeat)
    if hb is None:
        fail(result, "no HEARTBEAT from the autopilot")
    system, component = hb.get_srcSystem(), hb.get_srcComponent()
    result["heartbeat"] = {"system": system, "autopilot": hb.autopilot}
    result["frame_is_v2"] = hb.get_msgbuf()[0] == 0xFD

    pos = wait_for(conn, "LOCAL_POSITION_NED", 5)
    if pos is None:
        fail(result, "no LOCAL_POSITION_NED")
    result["position_ned"] = [pos.x, pos.y, pos.z]

    def command(cmd, *params):
        params = list(params) + [0.0] * (7 - len(params))
        conn.mav.command_long_send(system, component, cmd, 0, *params)
        ack = wait_for(conn, "COMMAND_ACK", 3, lambda m: m.command == cmd)
        return None if ack is None else ack.result

    result["arm_ack"] = command(mavutil.mavlink.MAV_CMD_COMPONENT_ARM_DISARM, 1)
    if result["arm_ack"] != 0:
        fail(result, "arm not accepted")

    # OFFBOARD before streaming: PX4 refuses.
    result["offboard_early_ack"] = command(mavutil.mavlink.MAV_CMD_DO_SET_MODE, 1, 6)

    start = time.time()

    def setpoint():
        conn.mav.set_position_target_local_ned_send(
            int((time.time() - start) * 1000), system, component,
            mavutil.mavlink.MAV_FRAME_LOCAL_NED, VELOCITY_ONLY,
            0, 0, 0, 0.5, 0, 0, 0, 0, 0, 0, 0)

    while time.time() - start < 1.5:
        setpoint()
        time.sleep(0.05)
    conn.mav.command_long_send(system, component, mavutil.mavlink.MAV_CMD_DO_SET_MODE, 0, 1, 6, 0, 0, 0, 0, 0)
    ack = wait_for(conn, "COMMAND_ACK", 3, lambda m: m.command == mavutil.mavlink.MAV_CMD_DO_SET_MODE, setpoint)
    result["offboard_ack"] = None if ack is None else ack.result
    hb = wait_for(conn, "HEARTBEAT", 3,
                  lambda m: m.get_srcSystem() == system and m.custom_mode == OFFBOARD, setpoint)
    result["offboard_heartbeat"] = hb is not None
    result["armed_heartbeat"] = hb is not None and bool(hb.base_mode & mavutil.mavlink.MAV_MODE_FLAG_SAFETY_ARMED)

    log = mavutil.mavlink_connection(args.tlog)
    counts = {}
    first_stamp = None
    while True:
        msg = log.recv_match(blocking=False)
        if msg is None:
            break
        counts[msg.get_type()] = counts.get(msg.get_type(), 0) + 1
        if first_stamp is None:
            first_stamp = msg._timestamp
    result["tlog_counts"] = counts
    result["tlog_first_timestamp"] = first_stamp

    ok = (result["offboard_ack"] == 0 and result["offboard_heartbeat"] and result["armed_heartbeat"]
          and result["offboard_early_ack"] == 1 and counts.get("HEARTBEAT", 0) > 0)
    if not ok:
        fail(result, "a step failed")
    print(json.dumps(result), flush=True)


if __name__ == "__main__":
    main()
