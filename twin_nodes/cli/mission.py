"""``rotortwin mission``: check, upload and start YAML mission plans with MAVSDK.

::

    rotortwin mission check PLAN.yaml [--home LAT,LON]
    rotortwin mission upload PLAN.yaml [--url udpin://0.0.0.0:14540] [--timeout 10]
    rotortwin mission start [--url udpin://0.0.0.0:14540] [--no-arm]
    rotortwin mission wait [--url udpin://0.0.0.0:14540] [--timeout 900]

Plans (format in twin_nodes/mavlink/mission.py; examples in missions/) hold
waypoints ``[north_m, east_m, alt_m]`` relative to home.  ``upload`` reads the
vehicle's home over the link (or uses the plan's ``home``, refusing one more
than 1 km from the vehicle's), uploads the items and the RTL-after flag.
``start`` arms (unless ``--no-arm``) and starts the mission; PX4 takes off by
itself.  ``wait`` returns once the vehicle has armed and disarmed again (landed after RTL).  ``--url`` takes MAVSDK URLs; the 1.x spelling ``udp://:14540`` is
accepted.
"""

from __future__ import annotations

import argparse

from twin_nodes.base.errors import TwinError
from twin_nodes.cli.options import SECONDS
from twin_nodes.cli.paths import declare
from twin_nodes.mavlink.mission import (
    DEFAULT_URL,
    load_plan,
    plan_to_mission_items,
    start_mission,
    upload_plan,
    wait_flight_done,
)
from twin_nodes.mavlink.sensors import SIH_ORIGIN_LAT_DEG, SIH_ORIGIN_LON_DEG


def register(subparsers: argparse._SubParsersAction) -> None:
    p = subparsers.add_parser("mission", help="check, upload and start mission plans (MAVSDK)",
                              description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    sub = p.add_subparsers(dest="mission_command", metavar="ACTION")
    p.set_defaults(func=lambda args: (p.print_help(), 2)[1])

    c = sub.add_parser("check", help="validate a plan and print its items as MAVSDK would upload them")
    declare(c).input("plan", help="plan YAML (e.g. missions/triangle.plan.yaml)")
    c.add_argument("--home", help="LAT,LON for the printout (default: the plan's home, else the SIH origin)")
    c.set_defaults(func=_cmd_check)

    u = sub.add_parser("upload", help="upload a plan to the vehicle")
    declare(u).input("plan", help="plan YAML")
    u.add_argument("--url", default=DEFAULT_URL, help=f"MAVSDK connection URL (default {DEFAULT_URL})")
    u.add_argument("--timeout", type=SECONDS, default=10.0, help="seconds to wait for the autopilot / home")
    u.set_defaults(func=_cmd_upload)

    s = sub.add_parser("start", help="arm and start the uploaded mission")
    s.add_argument("--url", default=DEFAULT_URL, help=f"MAVSDK connection URL (default {DEFAULT_URL})")
    s.add_argument("--no-arm", action="store_true", help="don't arm (the vehicle is armed already)")
    s.add_argument("--timeout", type=SECONDS, default=10.0, help="seconds to wait for the autopilot")
    s.set_defaults(func=_cmd_start)

    w = sub.add_parser("wait", help="wait until the vehicle has armed and disarmed again (mission flown)")
    w.add_argument("--url", default=DEFAULT_URL, help=f"MAVSDK connection URL (default {DEFAULT_URL})")
    w.add_argument("--arm-timeout", type=SECONDS, default=60.0, help="seconds to wait for arming (default 60)")
    w.add_argument("--timeout", type=SECONDS, default=900.0, help="seconds to wait for disarming (default 900)")
    w.set_defaults(func=_cmd_wait)


def _cmd_check(args: argparse.Namespace) -> int:
    plan = load_plan(args.plan)
    if args.home:
        try:
            lat, lon = (float(v) for v in args.home.split(","))
        except ValueError:
            raise TwinError(f"--home: expected LAT,LON in degrees, got {args.home!r}") from None
    elif plan.has_home:
        lat, lon = plan.home_lat_deg, plan.home_lon_deg
    else:
        lat, lon = SIH_ORIGIN_LAT_DEG, SIH_ORIGIN_LON_DEG
    print(f"{plan.source}: '{plan.name}', {len(plan.waypoints)} waypoints, {plan.length_m():.1f} m, "
          f"RTL after: {'yes' if plan.rtl_after else 'no'}; home {lat:.7f}, {lon:.7f}")
    for i, (wp, it) in enumerate(zip(plan.waypoints, plan_to_mission_items(plan, lat, lon))):
        print(f"  {i}: N {wp.north_m:8.2f}  E {wp.east_m:8.2f}  alt {wp.alt_m:6.1f} m -> "
              f"{it.latitude_deg:.7f}, {it.longitude_deg:.7f}  {wp.speed_m_s:g} m/s  "
              f"r {wp.acceptance_radius_m:g} m  {'fly-through' if wp.fly_through else 'stop'}")
    return 0


def _cmd_upload(args: argparse.Namespace) -> int:
    plan = load_plan(args.plan)
    out = upload_plan(plan, args.url, connect_timeout_s=args.timeout, home_timeout_s=args.timeout)
    print(f"uploaded '{out['name']}': {out['items']} items to {out['url']}, home {out['home'][0]:.7f}, "
          f"{out['home'][1]:.7f}, RTL after: {'yes' if out['rtl_after'] else 'no'}, current item 0 "
          f"({'confirmed' if out['current_item_confirmed'] else 'not confirmed'} by the vehicle)")
    return 0


def _cmd_start(args: argparse.Namespace) -> int:
    out = start_mission(args.url, arm=not args.no_arm, connect_timeout_s=args.timeout)
    print(f"mission started on {out['url']}{' (armed)' if out['armed'] else ''}")
    return 0


def _cmd_wait(args: argparse.Namespace) -> int:
    out = wait_flight_done(args.url, arm_timeout_s=args.arm_timeout, timeout_s=args.timeout)
    print(f"flight done on {out['url']}: armed for {out['flight_s']:.0f} s")
    return 0
