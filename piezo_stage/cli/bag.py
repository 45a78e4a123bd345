"""`piezo-stage bag`: check or repair a recorded bag."""

from __future__ import annotations

HELP = "check or repair a recorded bag"


def add_arguments(s):
    s.add_argument("action", choices=("check", "repair"))
    s.add_argument("bag", help="bag directory or .mcap file")


def main(args):
    from piezo_stage.io.bag import repair_bag, scan_bag
    if args.action == "check":
        scan = scan_bag(args.bag)
        print(f"{args.bag}: {len(scan.messages)} readable messages on "
              f"{len(scan.channels)} topics; {scan.damage() or 'intact'}")
        return 0 if not scan.damage() else 1
    scan = repair_bag(args.bag)
    print(f"{args.bag}: rewritten with {len(scan.messages)} messages on "
          f"{len(scan.channels)} topics, a summary and metadata.yaml (original kept as "
          f"*.orig); it had: {scan.damage() or 'no damage'}")
    return 0
