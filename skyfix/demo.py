"""``skyfix demo``: the main demonstration on the built-in multi-vehicle simulator.

Until the simulator, drivers, ranging and fusion have landed, the command says what
the demo will do and exits non-zero.
"""

from __future__ import annotations

import argparse
import sys

PLAN = """\
skyfix demo will:
  1. start the built-in multi-vehicle MAVLink simulator on loopback (3 quadcopters);
  2. connect to each vehicle with skyfix.drivers, arm, take off and fly a survey mission;
  3. cut GPS on one vehicle mid-flight; it broadcasts a help request;
  4. the two helpers fly towards it, observe it with their (rendered) cameras and
     measure range and bearing (skyfix.crps);
  5. the fusion core (skyfix.fusion) fuses the observations, the position is injected
     into the vehicle (GPS_INPUT) and it returns home;
  6. write a trajectory plot (PNG) and the measurement log for replay.
"""


def register(subparsers: argparse._SubParsersAction) -> None:
    p = subparsers.add_parser("demo", help="run the main demo on the built-in simulator",
                              description=PLAN, formatter_class=argparse.RawDescriptionHelpFormatter)
    p.set_defaults(func=run)


def run(args: argparse.Namespace) -> int:
    sys.stdout.write(PLAN)
    sys.stderr.write("skyfix demo: not available yet: the simulator, drivers, ranging and fusion "
                     "modules it needs have not landed. Nothing was run.\n")
    return 3
