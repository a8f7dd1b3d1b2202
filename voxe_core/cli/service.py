"""``voxe sweep``: the paper's protocol submitted to the job service (SPEC §4) over its HTTP API.

The one command that talks to the service: it imports ``voxe_client`` (the HTTP client) where it
runs, so the library itself holds no web code.
"""

from __future__ import annotations

import argparse
import json
import sys
from pathlib import Path

from voxe_core.cli.common import EXIT_INTERRUPTED, EXIT_USAGE, Interrupt


def _scene_object(text: str) -> dict:
    scene_id, sep, name = text.partition("=")
    if not sep or not scene_id.strip() or not name.strip():
        raise argparse.ArgumentTypeError(f"expected SCENE_ID=OBJECT (e.g. 3f2a...=microphone), got {text!r}")
    return {"scene_id": scene_id.strip(), "object": name.strip()}


def _json_object(text: str) -> dict:
    try:
        value = json.loads(text)
    except json.JSONDecodeError as exc:
        raise argparse.ArgumentTypeError(f"not JSON: {exc}") from None
    if not isinstance(value, dict):
        raise argparse.ArgumentTypeError(f"expected a JSON object, got {text!r}")
    return value


def add_parsers(commands, common) -> None:
    sw = commands.add_parser(
        "sweep", parents=[common],
        help="submit the paper's protocol to the service: scenes × the six prompts of SPEC §4, each edit evaluated",
    )
    sw.add_argument("--api", default="http://127.0.0.1:8000", metavar="URL", help="the service's base URL")
    sw.add_argument("--scene", type=_scene_object, action="append", required=True, metavar="SCENE_ID=OBJECT",
                    help="an uploaded scene and what its object is called in the prompts (repeat for several)")
    sw.add_argument("--params", type=_json_object, default=None, metavar="JSON", help="edit job params (POST /v1/jobs)")
    sw.add_argument("--evaluation", type=_json_object, default=None, metavar="JSON",
                    help='evaluation params, e.g. \'{"views": 100, "size": 266}\'')
    sw.add_argument("--api-key", default=None, help="API key (default: $VOXE_API_KEY; none needed on a loopback service)")
    sw.add_argument("--wait", action="store_true", help="poll until every job of the sweep is finished")
    sw.add_argument("--poll", type=float, default=10.0, help="seconds between polls with --wait")
    sw.add_argument("--out", type=Path, default=None, metavar="FILE", help="also write the final summary JSON here")
    sw.set_defaults(run=cmd_sweep)


def cmd_sweep(args) -> int:
    import os
    import time

    from voxe_client import Client, ServiceError

    with Client(args.api, api_key=args.api_key or os.environ.get("VOXE_API_KEY")) as client:
        try:
            sweep = client.create_sweep(args.scene, params=args.params, evaluation=args.evaluation)
            print(f"sweep {sweep['id']}: {len(sweep['entries'])} edits of {len(args.scene)} scene(s) queued, each "
                  f"followed by its evaluation; GET {client.base_url}/v1/sweeps/{sweep['id']}", file=sys.stderr)
            interrupt = Interrupt()
            with interrupt.installed():
                while args.wait and sweep["state"] in ("queued", "running") and not interrupt.requested:
                    if not args.quiet:
                        print(f"sweep {sweep['id']}: {sweep['state']}, jobs {sweep['counts']}", file=sys.stderr)
                    time.sleep(args.poll)
                    sweep = client.get_sweep(sweep["id"])
        except ServiceError as exc:
            print(f"voxe sweep: error: {exc}", file=sys.stderr)
            return EXIT_USAGE
    if args.out is not None:
        args.out.parent.mkdir(parents=True, exist_ok=True)
        args.out.write_text(json.dumps(sweep, indent=2))
    print(sweep["table"], end="")
    if interrupt.requested:
        print(f"voxe sweep: stopped waiting; the sweep {sweep['id']} goes on in the service", file=sys.stderr)
        return EXIT_INTERRUPTED
    return 0
