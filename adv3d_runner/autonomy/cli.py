"""``adv3d stacks``: the stacks under test adv3d can drive (docs/stacks.md)."""
from __future__ import annotations

import argparse
import json


def _list(args: argparse.Namespace) -> int:
    from ..errors import Adv3dError
    from .plugins import info_of, registered
    from .stacks import own_info

    rows = []
    for name, entry in registered().items():
        info = own_info(name)
        error = None
        if info is None:
            try:
                info = info_of(name)
            except Adv3dError as exc:  # a broken plugin is listed with its error, not a traceback
                error = str(exc)
        rows.append({"name": name, "target": entry.target, "source": entry.source,
                     **({"version": info.version, "provides": sorted(info.provides), "fingerprint": info.fingerprint}
                        if info is not None else {"error": error})})
    if args.json:
        print(json.dumps(rows, indent=1))
        return 0
    width = max(len(r["name"]) for r in rows)
    for r in rows:
        what = (f"{r['version']:<10} provides {', '.join(r['provides']) or 'a plan only'}; fingerprint "
                f"{r['fingerprint'] or '-'}" if "error" not in r else f"BROKEN: {r['error']}")
        print(f"{r['name']:<{width}}  {what}  [{r['source']}: {r['target']}]")
    return 0


def _info(args: argparse.Namespace) -> int:
    from .plugins import info_of

    info = info_of(args.stack)
    print(json.dumps(info.as_dict(), indent=1))
    return 0


def register(subparsers) -> None:
    from .names import stack_spec

    p = subparsers.add_parser("stacks", help="the stacks under test: list, info",
                              description="The autonomy stacks adv3d can test: its own (A, A-fast, A-lanefollow, B, "
                                          "oracle) and every plugin registered in the adv3d.stacks entry-point "
                                          "group (docs/stacks.md).")
    sub = p.add_subparsers(dest="stacks_command", metavar="COMMAND", required=True)
    lst = sub.add_parser("list", help="every registered stack with its version and fingerprint")
    lst.add_argument("--json", action="store_true", help="as JSON")
    lst.set_defaults(func=_list)
    info = sub.add_parser("info", help="one stack's info (a remote stack is started, asked and closed)")
    info.add_argument("stack", type=stack_spec, help="a registered name, package.module:factory, exec:COMMAND, "
                                                     "tcp://HOST:PORT or unix:PATH")
    info.set_defaults(func=_info)
