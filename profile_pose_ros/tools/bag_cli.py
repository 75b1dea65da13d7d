"""profile_pose_bag: what is in a bag (`info`), and finishing a bag whose recorder was killed
(`recover`: everything up to the recorder's last flush is kept; like `ros2 bag reindex`)."""
from __future__ import annotations

import argparse
import sys

from ..bags import BagError, bag_info, recover


def main(argv=None) -> int:
    parser = argparse.ArgumentParser(description=__doc__)
    sub = parser.add_subparsers(dest="command", required=True)
    sub.add_parser("info", help="topics, types, counts, duration").add_argument("bag")
    sub.add_parser("recover", help="finish a bag left open by a killed recorder").add_argument("bag")
    args = parser.parse_args(argv)
    try:
        if args.command == "recover":
            for line in recover(args.bag) or ["nothing to recover: the bag was closed"]:
                print(line)
        print(bag_info(args.bag).table())
    except BagError as exc:
        print(f"profile_pose_bag: {exc}", file=sys.stderr)
        return 2
    return 0


if __name__ == "__main__":
    sys.exit(main())
