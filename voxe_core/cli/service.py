"""The commands that talk to the job service over its HTTP API: ``voxe submit | status | wait | download |
cancel`` for one job, ``voxe sweep`` and ``voxe cancel-sweep`` for the paper's protocol (SPEC §4), ``voxe
webhook-secret [--rotate]`` for the key's webhook signing secret.

They import ``voxe_client`` (the HTTP client) where they run, so the library itself holds no web code. A request
the service refuses (4xx) exits 2, as any bad input; a service that failed (5xx) or was not reached exits 3.
"""

from __future__ import annotations

import argparse
import json
import math
import shutil
import sys
import time
import warnings
from pathlib import Path

from voxe_core.cli.common import (
    EXIT_FAILED, EXIT_INTERRUPTED, EXIT_SERVICE_FAILED, EXIT_USAGE, LOG_PROGRESS_INTERVAL_S, Interrupt,
    non_negative_seconds, positive_seconds, writable_file, writable_folder, write_json,
)
from voxe_core.presets import EDIT_MODE, EDIT_MODES, broken_job_option_rule


def _scene_object(text: str) -> dict:
    scene_id, sep, name = text.partition("=")
    if not sep or not scene_id.strip() or not name.strip():
        raise argparse.ArgumentTypeError(f"expected SCENE_ID=OBJECT (e.g. 3f2a...=microphone), got {text!r}")
    return {"scene_id": scene_id.strip(), "object": name.strip()}


class _NoJsonNumber(ValueError):
    """A number of a ``--params`` that no JSON request carries."""


def _finite_number(text: str) -> float:
    value = float(text)
    if not math.isfinite(value):
        raise _NoJsonNumber(f"the number {text} is past a float's range")
    return value


def _no_constant(name: str):
    raise _NoJsonNumber(f"{name} is no JSON number")


def _json_object(text: str) -> dict:
    """``--params`` and ``--evaluation``: a JSON object, or a usage error saying why not (nesting past the recursion
    limit had escaped argparse as a RecursionError traceback, and a number past Python's int-string limit had been
    "invalid _json_object value" quoting the whole text; 1e400, NaN or Infinity, which Python's json reads, had been
    refused only as the request was sent, "Out of range float values are not JSON compliant", no option named)."""
    try:
        value = json.loads(text, parse_float=_finite_number, parse_constant=_no_constant)
    except json.JSONDecodeError as exc:
        raise argparse.ArgumentTypeError(f"not JSON: {exc}") from None
    except _NoJsonNumber as exc:
        raise argparse.ArgumentTypeError(f"not JSON this command reads: {exc}") from None
    except RecursionError:
        raise argparse.ArgumentTypeError("not JSON this command reads: its arrays or objects nest too deeply") from None
    except ValueError:  # json.loads' only other ValueError: int() past the int-string limit
        raise argparse.ArgumentTypeError(f"not JSON this command reads: a number has more than "
                                         f"{sys.get_int_max_str_digits()} digits") from None
    if not isinstance(value, dict):
        raise argparse.ArgumentTypeError(f"expected a JSON object, got {text!r}")
    return value


def add_parsers(commands, common) -> None:
    service = argparse.ArgumentParser(add_help=False)
    service.add_argument("--api", default="http://127.0.0.1:8000", metavar="URL", help="the service's base URL")
    service.add_argument("--api-key", default=None,
                         help="API key (default: $VOXE_API_KEY; none needed on a loopback service)")

    sub = commands.add_parser("submit", parents=[common, service], help="create an edit job on the service")
    sub.add_argument("prompt")
    where = sub.add_mutually_exclusive_group(required=True)
    where.add_argument("--scene", metavar="SCENE_ID", help="an uploaded scene")
    where.add_argument("--upload", type=Path, metavar="PATH",
                       help="upload this dataset zip or mesh first (an OBJ with the .mtl and texture it names, a "
                            "PLY with the texture its header names; deleted again when the service refuses the job)")
    sub.add_argument("--texture", type=Path, default=None, metavar="IMAGE",
                     help="with --upload OBJ or PLY: the image that colours it at its UVs, instead of the one it "
                          "names (as mesh-to-grid --texture)")
    sub.add_argument("--scene-name", default=None, metavar="NAME",
                     help="with --upload: the scene's display name (default: the file's name without its suffix)")
    sub.add_argument("--up", choices=("x", "y", "z"), default=None,
                     help="with --upload OBJ or PLY: the mesh file's up axis (default y, as OBJ and glTF exports; z "
                          "for CAD and most scanners), as mesh-to-grid --up")
    sub.add_argument("--shading", choices=("auto", "baked", "none"), default=None,
                     help="with --upload OBJ or PLY: bake a fixed light + ambient occlusion into the colour (default "
                          "auto: for meshes without colour), as mesh-to-grid --shading")
    sub.add_argument("--mode", choices=EDIT_MODES, default=EDIT_MODE)
    sub.add_argument("--edit-word", action="append", default=[], metavar="WORD", help="local edits (repeat)")
    sub.add_argument("--params", type=_json_object, default=None, metavar="JSON", help="job params")
    sub.add_argument("--webhook-url", default=None, metavar="URL",
                     help="POST the job's events here, signed (the secret: voxe webhook-secret)")
    sub.add_argument("--webhook-event", action="append", default=None, metavar="EVENT",
                     help="with --webhook-url: a job event to send there (repeat; default succeeded, failed and "
                          "canceled; the others: stage_started, stage_completed, warning, artifact, preview)")
    sub.add_argument("--wait", action="store_true", help="follow the job's events until it ends")
    _add_reconnect_argument(sub)
    _add_idempotency_argument(sub, "the job (with --upload, also the scene) the first run made")
    sub.set_defaults(run=cmd_submit)
    for name, help_text in (("status", "the job's record as JSON"), ("wait", "follow the job's live events until "
                            "it ends (a progress bar on stderr)"), ("cancel", "cancel the job")):
        job = commands.add_parser(name, parents=[common, service], help=help_text)
        job.add_argument("job_id")
        if name == "wait":
            _add_reconnect_argument(job)
        job.set_defaults(run=cmd_job)
    dl = commands.add_parser("download", parents=[common, service],
                             help="download the job's artifacts, each size and SHA-256 checked")
    dl.add_argument("job_id")
    dl.add_argument("--name", action="append", default=None, metavar="NAME", help="only these artifacts (repeat)")
    dl.add_argument("--out", type=Path, default=Path("."), metavar="DIR")
    dl.set_defaults(run=cmd_download)

    sw = commands.add_parser(
        "sweep", parents=[common, service],
        help="submit the paper's protocol to the service: scenes × the six prompts of SPEC §4, each edit evaluated",
    )
    sw.add_argument("--scene", type=_scene_object, action="append", required=True, metavar="SCENE_ID=OBJECT",
                    help="an uploaded scene and what its object is called in the prompts (repeat for several)")
    sw.add_argument("--params", type=_json_object, default=None, metavar="JSON", help="edit job params (POST /v1/jobs)")
    sw.add_argument("--evaluation", type=_json_object, default=None, metavar="JSON",
                    help='evaluation params, e.g. \'{"views": 100, "size": 266}\'')
    sw.add_argument("--wait", action="store_true", help="poll until every job of the sweep is finished, then print "
                    "its summary table (without: the sweep's id, at once); polls through a service that stops "
                    "answering for up to 300 s")
    sw.add_argument("--poll", type=positive_seconds, default=None, metavar="SECONDS",  # checked before the sweep
                    help=f"with --wait: seconds between polls (default {SWEEP_POLL_S:g})")
    sw.add_argument("--out", type=Path, default=None, metavar="FILE",
                    help="also write the sweep's JSON here: with --wait its final summary (nothing is written when "
                         "the wait is interrupted, the sweep not ended), without it the sweep as queued")
    _add_idempotency_argument(sw, "the sweep the first run made")
    sw.set_defaults(run=cmd_sweep)

    cancel = commands.add_parser("cancel-sweep", parents=[common, service],
                                 help="cancel every unfinished job of a sweep (finished ones and their results stay)")
    cancel.add_argument("sweep_id")
    cancel.set_defaults(run=cmd_cancel_sweep)

    secret = commands.add_parser("webhook-secret", parents=[common, service],
                                 help="print the key's webhook signing secret (whsec_...: it verifies the "
                                      "deliveries to --webhook-url)")
    secret.add_argument("--rotate", action="store_true",
                        help="replace it first (a leaked one) and print the new one: every delivery attempt from now "
                             "on, a retry of an earlier one included, is signed with it")
    secret.set_defaults(run=cmd_webhook_secret)


def _add_reconnect_argument(parser: argparse.ArgumentParser) -> None:
    """``--reconnect-for``: how long following a job's events rides out a service that stopped answering."""
    parser.add_argument("--reconnect-for", type=non_negative_seconds, default=None, metavar="SECONDS",
                        help="while following the job, keep reconnecting to a service that stopped answering (an "
                             "API restart) this long before giving up (default 300; 0: give up at the first "
                             "loss; the job goes on in the service either way)")


def _add_idempotency_argument(parser: argparse.ArgumentParser, made: str) -> None:
    """``--idempotency-key``: a script that runs the command again after a failure gets back ``made``, not a second
    one (each run had sent a key of its own)."""
    parser.add_argument("--idempotency-key", default=None, metavar="KEY",
                        help=f"sent as the Idempotency-Key header: a run with the same KEY and request answers with "
                             f"{made} instead of making another (default: a new key each run; 1-255 characters)")


SWEEP_POLL_S = 10.0
"""Seconds between a waited sweep's polls, unless ``--poll`` says."""


def _client(args):
    import os

    from voxe_client import Client
    from voxe_client.client import NotAServiceURL

    try:
        return Client(args.api, api_key=args.api_key or os.environ.get("VOXE_API_KEY"))
    except NotAServiceURL as exc:  # (it had named no option)
        raise ValueError(f"--api: {exc}") from None


def _progress_bar(quiet: bool):
    """An ``on_progress`` callback drawing the job's overall progress on stderr: redrawn in place on a terminal,
    elsewhere (a log) a line at once whenever the job's state, stage or message (a phase of the stage: ``refine:
    attention_maps``) changes, and between those a line at most every ``LOG_PROGRESS_INTERVAL_S`` and only when it
    changed: a short job's log had shown only its first and last snapshot, none of the stages between."""
    from voxe_client.client import snapshot_number  # (lazy: tests/test_layers.py)

    terminal, last = sys.stderr.isatty(), {"line": None, "step": None, "at": -math.inf, "shown": 0}

    def draw(snapshot: dict) -> None:
        done = snapshot_number(snapshot.get("overall_progress"), 1.0)
        eta = snapshot_number(snapshot.get("overall_eta_seconds"))
        state, stage, message = snapshot.get("state"), snapshot.get("stage"), snapshot.get("message")
        bar = "#" * round(30 * (done or 0.0))
        share = "  ?  %" if done is None else f"{100 * done:5.1f}%"
        line = " ".join(str(part) for part in (f"[{bar:<30}] {share}", state, stage,
                                               eta is not None and f"~{eta:.0f} s left", message and f"- {message}")
                        if part)
        now, step = time.monotonic(), (state, stage, message)
        if quiet or line == last["line"] or (not terminal and step == last["step"]
                                             and now - last["at"] < LOG_PROGRESS_INTERVAL_S):
            return
        if terminal:  # within one row (a wrapped line is not redrawn in place), over all of the one before
            width = shutil.get_terminal_size().columns - 1  # (read each time: the terminal may have narrowed)
            shown = line[:width]
            print(f"\r{shown.ljust(min(last['shown'], width))}", end="", file=sys.stderr, flush=True)
            last["shown"] = len(shown)
        else:
            print(line, file=sys.stderr, flush=True)
        last.update(line=line, step=step, at=now)
    return draw


def _follow(client, job_id: str, args) -> int:
    """Follow the job to its end (``args``: --quiet, --reconnect-for); 0 when it succeeded, 1 when it did not, 130
    when Ctrl-C stopped the following (not the job)."""
    from voxe_client.client import EventStreamLost

    over_the_bar = not args.quiet and sys.stderr.isatty()

    def say_aside(line: str) -> None:
        """Says the stream lost and back, or a stage's warning, on a line of its own (even with --quiet: the bar had
        frozen, nothing said); on a terminal over the bar's row, the bar drawn again below."""
        text = f"voxe {args.command}: {line}"
        if over_the_bar:
            text = "\r" + text.ljust(shutil.get_terminal_size().columns - 1)
        print(text, file=sys.stderr, flush=True)

    draw, drawn = _progress_bar(args.quiet), [False]

    def on_progress(snapshot: dict) -> None:
        draw(snapshot)
        drawn[0] = True  # (over the bar: the first snapshot is always drawn)

    try:
        job = client.wait(job_id, on_progress=on_progress, reconnect_for=args.reconnect_for, on_reconnect=say_aside,
                          on_warning=lambda event: say_aside(f"{event.get('stage')}: {event.get('detail')}"))
    except KeyboardInterrupt:  # ("voxe: interrupted" had read as if the job were stopped too)
        print(f"\nvoxe {args.command}: stopped following; the job {job_id} goes on in the service (`voxe cancel "
              f"{job_id}` stops it)", file=sys.stderr)
        return EXIT_INTERRUPTED
    except Exception as exc:
        if over_the_bar and drawn[0]:  # ends the bar's row: the error had been written on it, after the bar
            print(file=sys.stderr)
        if isinstance(exc, EventStreamLost):
            raise EventStreamLost(f"{exc}: `voxe wait {job_id}` follows it again (--reconnect-for SECONDS rides "
                                  "out a longer outage)") from None
        raise
    if over_the_bar:  # ends the bar redrawn in place; a log's lines end themselves
        print(file=sys.stderr)
    print_json(job)
    return 0 if job["state"] == "succeeded" else EXIT_FAILED


def cmd_submit(args) -> int:
    from voxe_client import ServiceError
    from voxe_client.client import MissingCompanionWarning, scene_upload_files

    if args.upload is None and (given := [option for option, value in (("--texture", args.texture),
                                                                       ("--up", args.up), ("--shading", args.shading))
                                          if value is not None]):
        raise ValueError(f"{given[0]} goes with --upload (an OBJ or a PLY); an uploaded scene keeps its colours and "
                         "its up axis")
    if args.scene_name is not None and args.upload is None:  # (an uploaded scene keeps its name)
        raise ValueError("--scene-name names the scene --upload makes; --scene is one uploaded, named already")
    if args.reconnect_for is not None and not args.wait:  # (it had been taken and ignored, as sweep's --poll was)
        raise ValueError("--reconnect-for sets how long --wait rides out a lost event stream: pass --wait too")
    if args.upload is not None:
        _check_job_options(args)
    fields = {"mode": args.mode, "edit_words": args.edit_word}
    fields.update({k: v for k, v in (("params", args.params), ("webhook_url", args.webhook_url),
                                     ("webhook_events", args.webhook_event))
                   if v is not None})  # (an empty --webhook-url "$UNSET" had been dropped, the job made)
    with _client(args) as client:
        try:
            scene_id = args.scene
            if args.upload is not None:
                with warnings.catch_warnings():  # (said as the upload reads the mesh's companions again)
                    warnings.simplefilter("ignore", MissingCompanionWarning)
                    scene_upload_files(args.upload, args.texture)  # a file it cannot send: before asking the service
                try:  # (a bad --params had been refused once the whole upload was stored, the scene deleted again)
                    client.check_job(args.prompt, **fields)
                except ServiceError as exc:
                    raise type(exc)(f"{exc}; nothing uploaded", exc.status, exc.detail) from None
                with warnings.catch_warnings(record=True) as left_out:  # a mesh's .mtl or texture not found
                    warnings.simplefilter("always", MissingCompanionWarning)
                    scene_id = client.upload_scene(args.upload, name=args.scene_name, texture=args.texture,
                                                   idempotency_key=args.idempotency_key, mesh_shading=args.shading,
                                                   mesh_up_axis=args.up)["id"]
                for warning in left_out:
                    if issubclass(warning.category, MissingCompanionWarning):
                        print(f"voxe submit: warning: {warning.message}", file=sys.stderr)
                    else:  # as it would have been shown
                        warnings.showwarning(warning.message, warning.category, warning.filename, warning.lineno)
                print(f"uploaded {args.upload}: scene {scene_id}", file=sys.stderr)
            try:
                job = client.create_job(scene_id, args.prompt, idempotency_key=args.idempotency_key, **fields)
            except ServiceError as exc:
                if args.upload is None:
                    raise
                raise type(exc)(f"{exc}; {_after_refusal(client, scene_id, exc, args.idempotency_key)}", exc.status,
                                exc.detail) from None
            print(f"job {job['id']}: {job['state']}", file=sys.stderr)
            if args.wait:
                return _follow(client, job["id"], args)
            print(job["id"])
            return 0
        except ServiceError as exc:
            return _service_error("submit", exc)


def _check_job_options(args) -> None:
    """ValueError for options the service refuses in any job (``POST /v1/jobs``' rules), said before ``--upload``
    sends the scene: ``voxe submit P --upload big.zip --mode local`` (no --edit-word) had been refused once the whole
    upload was stored, the scene then deleted again, to be uploaded once more with the option fixed. The rules are
    the service's own (``presets.broken_job_option_rule``), said by their options."""
    if broken := broken_job_option_rule(args.mode, args.edit_word, args.webhook_url, args.webhook_event):
        raise ValueError(f"{JOB_OPTION_RULES[broken]}; nothing uploaded")


JOB_OPTION_RULES = {
    "edit_words_required": "--mode local needs --edit-word: the word(s) of the prompt naming the edit",
    "edit_words_local_only": "--edit-word applies to local edits only (--mode local)",
    "webhook_events_need_url": "--webhook-event needs a --webhook-url to send the events to",
}
"""``presets.JOB_OPTION_RULES`` as ``voxe submit`` says them (its options')."""


def _service_error(command: str, error) -> int:
    """Says the service's ``error`` on stderr; the exit status: ``EXIT_SERVICE_FAILED`` where the service failed (5xx)
    or was not reached, ``EXIT_USAGE`` where it refused the request (4xx) or the command refused its answer (both
    had exited 2, so a script could not tell an outage to try again from its own bad input)."""
    print(f"voxe {command}: error: {error}", file=sys.stderr)
    return EXIT_SERVICE_FAILED if error.service_failed else EXIT_USAGE


def _after_refusal(client, scene_id: str, refusal, idempotency_key: str | None) -> str:
    """What became of the scene ``voxe submit --upload`` uploaded for a job the service did not take: deleted when
    the service refused the job (a 4xx: no job was made, and the scene had stayed behind, counting towards the key's
    upload quota), else kept for ``--scene`` (the service may have made the job before the answer was lost). One sent
    with an ``idempotency_key`` stays too: it may be an earlier run's scene answered again, with that run's job, and
    a run with the key takes it up again."""
    from voxe_client import ServiceError

    if refusal.status is None or not 400 <= refusal.status < 500:
        return f"the scene {scene_id} this command uploaded stays (use it with --scene {scene_id})"
    if idempotency_key is not None:
        return (f"the scene {scene_id} stays: a run with --idempotency-key {idempotency_key!r} takes it up again, "
                f"as --scene {scene_id} does")
    try:
        client.delete_scene(scene_id)
    except ServiceError as exc:
        return f"the scene {scene_id} this command uploaded stays, its deletion failed ({exc})"
    return f"the scene {scene_id} this command uploaded is deleted"


def print_json(record: dict) -> None:
    """A job's or a sweep's record on stdout as indented JSON, its text in UTF-8 ("a café", not "a caf\\u00e9" as
    ``json.dumps`` escapes it by default); where stdout cannot encode a character (LANG=C: ASCII), the JSON escapes
    it, the same values, rather than fail the command once the service has answered."""
    text = json.dumps(record, indent=2, ensure_ascii=False)
    try:
        text.encode(sys.stdout.encoding or "utf-8")
    except UnicodeEncodeError:
        text = json.dumps(record, indent=2)
    print(text)


def cmd_job(args) -> int:
    """``voxe status | wait | cancel JOB_ID``."""
    from voxe_client import ServiceError

    with _client(args) as client:
        try:
            if args.command == "wait":
                return _follow(client, args.job_id, args)
            job = client.cancel_job(args.job_id) if args.command == "cancel" else client.get_job(args.job_id)
        except ServiceError as exc:
            return _service_error(args.command, exc)
    print_json(job)
    return 0


def cmd_download(args) -> int:
    from voxe_client.client import TERMINAL_STATES, ServiceError

    writable_folder(args.out)  # (made, it goes again when nothing is downloaded into it)
    with _client(args) as client:
        try:
            state = client.get_job(args.job_id)["state"]  # before the listing: an artifact it adds after is in it
            listed = {a["name"]: a for a in client.artifacts(args.job_id)}
            names = list(dict.fromkeys(args.name or listed))  # each once: --name a --name a had downloaded a twice
            if missing := [name for name in names if name not in listed]:  # before any is downloaded
                raise ServiceError(f"job {args.job_id} has no artifact {', '.join(map(repr, missing))}; it has "
                                   f"{', '.join(sorted(listed)) or 'none'}; nothing downloaded")
            for name in names:
                path = client.download(args.job_id, name, args.out / name, listed=listed[name])
                if not args.quiet:
                    print(f"{path} (sha256 checked)", file=sys.stderr)
        except ServiceError as exc:
            return _service_error("download", exc)
        except KeyboardInterrupt as exc:  # (its words say the bytes kept for the next run, and where)
            print(f"\nvoxe download: {exc or 'interrupted'}", file=sys.stderr)
            return EXIT_INTERRUPTED
    if state not in TERMINAL_STATES:  # (a download right after submit had exited 0 with a job's first few files)
        print(f"voxe download: note: job {args.job_id} is {state}: "
              f"{'these are the artifacts it has so far' if listed else 'it has no artifacts yet'}; `voxe wait "
              f"{args.job_id}`, then download again for all of them", file=sys.stderr)
    elif not listed:
        print(f"voxe download: note: job {args.job_id} {state} with no artifacts: nothing downloaded", file=sys.stderr)
    return 0


def cmd_cancel_sweep(args) -> int:
    """``voxe cancel-sweep SWEEP_ID``: the sweep's record as JSON, its jobs' states after the cancel."""
    from voxe_client import ServiceError

    with _client(args) as client:
        try:
            sweep = client.cancel_sweep(args.sweep_id)
        except ServiceError as exc:
            return _service_error(args.command, exc)
    print_json(sweep)
    return 0


def cmd_webhook_secret(args) -> int:
    """``voxe webhook-secret [--rotate]``: the secret alone on stdout, for a receiver's configuration."""
    from voxe_client import ServiceError

    with _client(args) as client:
        try:
            secret = client.rotate_webhook_secret() if args.rotate else client.webhook_secret()
        except ServiceError as exc:
            return _service_error(args.command, exc)
    print(secret)
    return 0


def _poll_failed(error, failing_since: float | None) -> float:
    """Since when a waited sweep's polls fail, ``error`` the latest, said on its first: one poll the service failed
    or did not answer (an API restart) had ended the wait, which no command takes up again. ``error`` itself once
    they have failed for ``RECONNECT_FOR_S`` (as ``voxe wait``'s event stream), or when the service refused it."""
    from voxe_client.client import RECONNECT_FOR_S

    now = time.monotonic()
    if not error.service_failed or failing_since is not None and now - failing_since >= RECONNECT_FOR_S:
        raise error
    if failing_since is not None:
        return failing_since
    print(f"voxe sweep: {error}; polling on for up to {RECONNECT_FOR_S:g} s (the sweep goes on in the service)",
          file=sys.stderr)
    return now


def cmd_sweep(args) -> int:
    from voxe_client import ServiceError
    from voxe_core.files import replacing

    if args.poll is not None and not args.wait:  # (it had been taken and ignored: the command returned at once)
        raise ValueError("--poll sets the seconds between the polls of --wait: pass --wait too")
    if args.out is not None:  # before the sweep is created: a bad --out had failed once it was queued (and waited)
        writable_file(args.out)
    with _client(args) as client:
        try:
            sweep = client.create_sweep(args.scene, params=args.params, evaluation=args.evaluation,
                                        idempotency_key=args.idempotency_key)
            print(f"sweep {sweep['id']}: {len(sweep['entries'])} edits of {len(args.scene)} scene(s) queued, each "
                  f"followed by its evaluation; GET {client.base_url}/v1/sweeps/{sweep['id']}", file=sys.stderr)
            interrupt, failing_since = Interrupt(), None
            with interrupt.installed():
                while args.wait and sweep["state"] in ("queued", "running") and not interrupt.requested:
                    if not args.quiet and failing_since is None:  # (not again what the last answer said)
                        print(f"sweep {sweep['id']}: {sweep['state']}, jobs {sweep['counts']}", file=sys.stderr)
                    interrupt.sleep(args.poll or SWEEP_POLL_S)
                    if interrupt.requested:  # no poll after a Ctrl-C: a hung service's would hold it up
                        break
                    try:
                        sweep, failing_since = client.get_sweep(sweep["id"]), None
                    except ServiceError as exc:
                        failing_since = _poll_failed(exc, failing_since)
        except ServiceError as exc:
            return _service_error("sweep", exc)
    # (a Ctrl-C's had written the last poll's, a sweep still running, where the final summary was promised)
    unfinished = interrupt.requested and sweep["state"] in ("queued", "running")
    if args.out is not None and not unfinished:
        with replacing(args.out) as partial:  # whole or not at all: a full disk had left it torn
            write_json(partial, sweep)
    if not args.wait:  # just queued: its table had been printed with no row, the sweep's id nowhere on stdout
        print(f"voxe sweep: not waited for (--wait polls until it ends): GET /v1/sweeps/{sweep['id']} shows its "
              "summary table as its evaluations finish", file=sys.stderr)
        print(sweep["id"])
        return 0
    print(sweep["table"], end="")
    if interrupt.requested:
        if args.out is not None and unfinished:
            print(f"voxe sweep: {args.out} not written: the sweep had not ended (GET /v1/sweeps/{sweep['id']} gives "
                  "its summary)", file=sys.stderr)
        print(f"voxe sweep: stopped waiting; the sweep {sweep['id']} goes on in the service (`voxe cancel-sweep "
              f"{sweep['id']}` stops it)", file=sys.stderr)
        return EXIT_INTERRUPTED
    if sweep["state"] != "succeeded":  # as voxe wait: a script must see what did not succeed
        print(f"voxe sweep: the sweep {sweep['id']} ended {sweep['state']}: jobs {sweep['counts']}", file=sys.stderr)
        return EXIT_FAILED
    return 0
