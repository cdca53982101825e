#!/usr/bin/env python3
"""MAVSDK conformance flight: MAVSDK's Python API (the mavsdk-grpc 4.0.5 wheel, which bundles
mavsdk_server; imported as mavsdk_grpc) connects to a vehicle, reads health and telemetry, arms,
takes off, flies offboard velocity, holds and lands.

usage: mavsdk_flight.py [URL] [--own-server] [--strict] [--time-scale K]
  URL default udpin://0.0.0.0:14540
Every call prints one line: CALL <name> OK|FAIL <detail>, then SUMMARY failed=...
Exit 2 on the first failure of an essential step; with --strict also when any call failed
(telemetry and identity included), as the conformance test runs it against the mock PX4.
"""
import argparse
import asyncio
import logging
import os
import socket
import sys
import time

from mavsdk_grpc import System
from mavsdk_grpc.offboard import OffboardError, VelocityNedYaw

T0 = time.monotonic()
FAILED = []


def out(line):
    print("[%6.1fs] %s" % (time.monotonic() - T0, line), flush=True)


class Essential(Exception):
    pass


async def first(agen, timeout):
    """First item of a MAVSDK stream, with a timeout."""
    async def _f():
        async for x in agen:
            return x
    return await asyncio.wait_for(_f(), timeout)


async def wait_until(agen, pred, timeout):
    """Consume a stream until pred(item) is true; returns that item."""
    async def _f():
        async for x in agen:
            if pred(x):
                return x
    return await asyncio.wait_for(_f(), timeout)


async def call(name, coro, timeout, essential=True, fmt=repr):
    try:
        res = await asyncio.wait_for(coro, timeout)
    except asyncio.TimeoutError:
        out("CALL %s FAIL timeout after %.0fs" % (name, timeout))
        FAILED.append(name)
        if essential:
            raise Essential(name)
        return None
    except Exception as e:  # ActionError, OffboardError, TelemetryError, grpc errors
        out("CALL %s FAIL %s: %s" % (name, type(e).__name__, str(e).replace("\n", " ")))
        FAILED.append(name)
        if essential:
            raise Essential(name)
        return None
    detail = (fmt(res) if fmt is not repr else str(res)) if res is not None else ""
    out("CALL %s OK %s" % (name, str(detail).replace("\n", " ")))
    return res


def free_port():
    s = socket.socket()
    s.bind(("127.0.0.1", 0))
    p = s.getsockname()[1]
    s.close()
    return p


def start_own_server(url, port, logpath):
    """Start the wheel's bundled mavsdk_server ourselves, with PR_SET_PDEATHSIG so it
    can never outlive this script (System()'s own spawn does not do that)."""
    import ctypes
    import signal
    import subprocess
    import mavsdk_grpc.bin as b
    exe = os.path.join(os.path.dirname(b.__file__), "mavsdk_server")
    libc = ctypes.CDLL("libc.so.6", use_errno=True)

    def pre():
        libc.prctl(1, signal.SIGKILL)  # PR_SET_PDEATHSIG

    log = open(logpath, "wb")
    return subprocess.Popen([exe, "-p", str(port), url], stdout=log, stderr=subprocess.STDOUT, preexec_fn=pre)


async def run(args, holder):
    k = args.time_scale  # multiply wall timeouts (slow CI)
    port = args.grpc_port or free_port()
    if args.own_server:
        holder["proc"] = start_own_server(args.url, port, args.server_log)
        drone = System(mavsdk_server_address="127.0.0.1", port=port)
        # channel_ready() blocks until mavsdk_server opens gRPC, which it only does
        # after the first heartbeat of a system has been received.
        await call("connect", drone.connect(), 30 * k)
    else:
        # connect() spawns the bundled mavsdk_server (-p port --sysid 245 --compid 190 URL)
        drone = System(port=port)
        holder["drone"] = drone
        await call("connect", drone.connect(system_address=args.url), 30 * k)
    await call("core.connection_state", wait_until(drone.core.connection_state(), lambda s: s.is_connected, 10 * k),
               10 * k)

    t = drone.telemetry
    await call("telemetry.health", first(t.health(), 10 * k), 10 * k, essential=False)
    await call("telemetry.position", first(t.position(), 10 * k), 10 * k, essential=False)
    await call("telemetry.attitude_euler", first(t.attitude_euler(), 10 * k), 10 * k, essential=False)
    await call("telemetry.battery", first(t.battery(), 10 * k), 10 * k, essential=False)
    await call("telemetry.flight_mode", first(t.flight_mode(), 10 * k), 10 * k, essential=False)
    await call("telemetry.landed_state", first(t.landed_state(), 10 * k), 10 * k, essential=False)
    await call("telemetry.in_air", first(t.in_air(), 10 * k), 10 * k, essential=False)
    await call("telemetry.armed", first(t.armed(), 10 * k), 10 * k, essential=False)
    await call("telemetry.home", first(t.home(), 10 * k), 10 * k, essential=False)
    await call("info.get_version", drone.info.get_version(), 10 * k, essential=False)
    await call("info.get_identification", drone.info.get_identification(), 10 * k, essential=False)
    await call("info.get_product", drone.info.get_product(), 10 * k, essential=False)

    # Wait (bounded) for health so that arming has a chance
    await call("telemetry.health_all_ok(wait)",
               wait_until(t.health_all_ok(), lambda ok: ok, 60 * k), 60 * k, essential=False)
    await call("telemetry.health(is_armable wait)",
               wait_until(t.health(), lambda h: h.is_armable, 30 * k), 30 * k, essential=False)

    await call("action.set_takeoff_altitude", drone.action.set_takeoff_altitude(2.0), 10 * k)
    await call("action.get_takeoff_altitude", drone.action.get_takeoff_altitude(), 10 * k, essential=False)

    # ArduPilot: retry arming a few times (prearm checks may still be settling)
    armed = False
    for attempt in range(args.arm_retries):
        try:
            await call("action.arm", drone.action.arm(), 15 * k)
            armed = True
            break
        except Essential:
            if attempt + 1 < args.arm_retries:
                FAILED.pop()
                await asyncio.sleep(3)
    if not armed:
        raise Essential("action.arm")
    await call("telemetry.armed(wait true)", wait_until(t.armed(), lambda a: a, 10 * k), 10 * k)

    await call("action.takeoff", drone.action.takeoff(), 15 * k)
    await call("telemetry.in_air(wait true)", wait_until(t.in_air(), lambda a: a, 30 * k), 30 * k)
    await call("telemetry.position(wait rel_alt>=1.5)",
               wait_until(t.position(), lambda p: p.relative_altitude_m >= 1.5, 60 * k), 60 * k,
               fmt=lambda p: "rel_alt=%.2f" % p.relative_altitude_m)
    await call("telemetry.flight_mode(after takeoff)", first(t.flight_mode(), 5 * k), 5 * k, essential=False)

    # Offboard: setpoint must be set before start()
    await call("offboard.set_velocity_ned(initial 0)", drone.offboard.set_velocity_ned(VelocityNedYaw(0, 0, 0, 0)),
               5 * k)
    await call("offboard.start", drone.offboard.start(), 15 * k)
    await call("offboard.is_active", drone.offboard.is_active(), 5 * k, essential=False)
    await call("telemetry.flight_mode(offboard)", first(t.flight_mode(), 5 * k), 5 * k, essential=False)
    p0 = await call("telemetry.position_velocity_ned(before)", first(t.position_velocity_ned(), 5 * k), 5 * k,
                    essential=False, fmt=lambda p: "n=%.2f e=%.2f d=%.2f" % (
                        p.position.north_m, p.position.east_m, p.position.down_m))
    await call("offboard.set_velocity_ned(1 m/s N)", drone.offboard.set_velocity_ned(VelocityNedYaw(1.0, 0, 0, 0)),
               5 * k)
    await asyncio.sleep(3.0)
    v = await call("telemetry.velocity_ned(during)", first(t.velocity_ned(), 5 * k), 5 * k, essential=False,
                   fmt=lambda v: "vn=%.2f ve=%.2f vd=%.2f" % (v.north_m_s, v.east_m_s, v.down_m_s))
    await call("offboard.set_velocity_ned(hold 0)", drone.offboard.set_velocity_ned(VelocityNedYaw(0, 0, 0, 0)), 5 * k)
    await asyncio.sleep(2.0)
    p1 = await call("telemetry.position_velocity_ned(after)", first(t.position_velocity_ned(), 5 * k), 5 * k,
                    essential=False, fmt=lambda p: "n=%.2f e=%.2f d=%.2f" % (
                        p.position.north_m, p.position.east_m, p.position.down_m))
    if p0 is not None and p1 is not None:
        dn = p1.position.north_m - p0.position.north_m
        ok = dn > 0.5
        out("CALL offboard.moved_north %s dn=%.2f m" % ("OK" if ok else "FAIL", dn))
        if not ok:
            FAILED.append("offboard.moved_north")
    await call("offboard.stop", drone.offboard.stop(), 15 * k)

    await call("action.land", drone.action.land(), 15 * k)
    await call("telemetry.in_air(wait false)", wait_until(t.in_air(), lambda a: not a, 90 * k), 90 * k)
    await call("telemetry.landed_state(after)", first(t.landed_state(), 5 * k), 5 * k, essential=False)
    await call("telemetry.armed(wait false)", wait_until(t.armed(), lambda a: not a, 60 * k), 60 * k)
    return drone


async def main():
    ap = argparse.ArgumentParser()
    ap.add_argument("url", nargs="?", default="udpin://0.0.0.0:14540")
    ap.add_argument("--grpc-port", type=int, default=0)
    ap.add_argument("--time-scale", type=float, default=1.0)
    ap.add_argument("--arm-retries", type=int, default=5)
    ap.add_argument("--verbose", action="store_true", help="python-side debug log (mavsdk_server log when not --own-server)")
    ap.add_argument("--own-server", action="store_true", help="spawn mavsdk_server ourselves (dies with us)")
    ap.add_argument("--server-log", default="mavsdk_server.log")
    ap.add_argument("--strict", action="store_true", help="any failed call fails the run")
    args = ap.parse_args()
    if args.verbose:
        logging.basicConfig(level=logging.DEBUG, format="%(name)s: %(message)s")
    holder = {}
    rc = 0
    try:
        await asyncio.wait_for(run(args, holder), 600 * args.time_scale)
    except Essential as e:
        out("ESSENTIAL FAILURE: %s" % e)
        rc = 2
    except asyncio.TimeoutError:
        out("ESSENTIAL FAILURE: overall timeout")
        rc = 2
    finally:
        if "proc" in holder:
            holder["proc"].kill()
        if "drone" in holder:
            holder["drone"]._stop_mavsdk_server()
    out("SUMMARY failed=%s" % (",".join(FAILED) or "none"))
    if args.strict and FAILED:
        rc = 2
    return rc


if __name__ == "__main__":
    rc = asyncio.run(main())
    # System.__del__ kills mavsdk_server; make sure it is gone even on odd exits.
    sys.stdout.flush()
    os._exit(rc)
