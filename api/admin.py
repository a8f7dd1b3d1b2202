"""Admin commands for API keys, run on a machine with the service's settings (VOXE_DATABASE_URL).

    python -m api.admin create-key --name alice [--max-active-jobs 5] [--max-upload-bytes 10000000000]
        [--expires-in 90d]
    python -m api.admin list-keys
    python -m api.admin update-key <key id or token> [--max-active-jobs 10|default] [--max-upload-bytes N|default]
        [--expires-in 30d | --never-expires]
    python -m api.admin rotate-webhook-secret <key id or token>
    python -m api.admin revoke-key <key id or token>

``create-key`` prints the token once; only its sha256 is stored, so a lost token means a new key. A key created with
``--expires-in`` is refused from then on (401 saying it expired), its jobs and scenes kept. ``update-key`` changes a
key's quotas (the next request is held to them) or expiry, its token unchanged; ``rotate-webhook-secret`` its webhook
signing secret (its holder reads the new one at GET /v1/webhooks/secret). ``revoke-key`` also cancels the key's
unfinished jobs and fails its scenes still processing.
"""

from __future__ import annotations

import argparse
import re
import sys
import unicodedata
from datetime import timedelta

from sqlalchemy import select
from sqlalchemy.orm import Session

from api.auth import TOKEN_PREFIX, create_key, has_expired, key_of_token, token_key_id
from api.services.jobs import request_cancel, rotate_webhook_secret
from voxe_service.db import DATABASE_UNAVAILABLE, outage_line, run_migrations, session_scope
from voxe_service.models import LOCAL_KEY_ID, PROCESSING, TERMINAL_STATES, ApiKey, Job, Scene, utcnow
from voxe_service.scenes import fail_scene
from voxe_service.settings import SettingsError, get_settings, refuse_settings
from voxe_service.storage import get_storage, scene_key


def _count_up_to(most: int, or_default: bool = False):
    """An argument type for a count from 1 to ``most``, the largest its database column holds: more had ended the
    command in a traceback (SQLite's OverflowError, PostgreSQL's "integer out of range"). ``or_default``: "default"
    is taken too, as None (the key goes back to the setting's value)."""

    def count(text: str) -> int | None:
        if or_default and text == "default":
            return None
        try:
            value = int(text)
        except ValueError:
            whole = "a whole number or 'default'" if or_default else "a whole number"
            raise argparse.ArgumentTypeError(f"must be {whole}, got {text!r}") from None
        if not 1 <= value <= most:
            raise argparse.ArgumentTypeError(f"must be 1 to {most}, got {value}")
        return value

    return count


_DURATION = re.compile(r"(\d+)([smhd])")
_UNIT_S = {"s": 1, "m": 60, "h": 3600, "d": 86400}
MOST_LIFETIME_D = 36500


def _lifetime(text: str) -> timedelta:
    """An argument type for how long a key lasts from now: a whole number of seconds, minutes, hours or days ("90d",
    "12h"), 1 s to 100 years (a later end would not be an expiry, and past year 9999 no datetime holds it)."""
    if (match := _DURATION.fullmatch(text.strip())) is None:
        raise argparse.ArgumentTypeError(f"must be a whole number of s, m, h or d (e.g. 90d, 12h), got {text!r}")
    digits, unit = match.groups()
    seconds = int(digits) * _UNIT_S[unit] if len(digits) <= 12 else None
    if seconds is None or not 1 <= seconds <= MOST_LIFETIME_D * _UNIT_S["d"]:
        raise argparse.ArgumentTypeError(f"must be 1s to {MOST_LIFETIME_D}d (100 years), got {text!r}")
    return timedelta(seconds=seconds)


def name_problem(name: str) -> str | None:
    """Why ``name`` cannot name a key, None when it can: 1 to 255 characters (its column's), none a control, format
    or line-breaking character (a tab, a newline or a bidi override would forge or reorder list-keys' rows). Any
    space separator is fine: str.isprintable had refused a no-break or ideographic space ("山田\u3000太郎")."""
    if not 1 <= len(name) <= 255:
        return f"must be 1-255 characters, got {len(name)}"
    for at, char in enumerate(name):
        if not (char.isprintable() or unicodedata.category(char) == "Zs"):
            return (f"must hold no control, format or line-breaking character (one would forge list-keys' rows), "
                    f"got {char!r} at {at}")
    return None


LISTED = " (python -m api.admin list-keys shows them)"


def key_named(session: Session, given: str, *, local: str | None = "it has no token to revoke (VOXE_AUTH=on requires a "
              "key of every request)") -> tuple[ApiKey | None, str]:
    """The key ``given`` names, by its id or by its token (what one holding a leaked token has: it had been looked
    up as an id and printed back, secret and all), and else what to say, never quoting a token's secret. ``local``:
    why the command does not apply to the built-in local key (None: it does).

    The spaces and line ending around it are cut, as around a --name: a token pasted with a space or read from a line
    ending in CR LF had been printed back whole ("no API key ' voxe_<id>_<secret>'"), one ending in a newline refused
    as "no API key has this token", the key left live. Other text holding "voxe_" (a pasted "Bearer voxe_...") is not
    quoted: no key id holds it, and it may hold a secret."""
    given = given.strip()
    if (key_id := token_key_id(given)) is not None:
        return key_of_token(session, given), f"no API key has this token (of key id {key_id!r}){LISTED}"
    if TOKEN_PREFIX in given:
        return None, (f"no API key: the text given holds {TOKEN_PREFIX!r} but is no token ({TOKEN_PREFIX}<key id>_"
                      f"<secret>) nor a key id (not quoted: it may hold a secret){LISTED}")
    if given == LOCAL_KEY_ID and local is not None:  # (it had been "no API key 'local'", a key requests act as)
        return None, f"{LOCAL_KEY_ID!r} is the built-in key that requests act as with authentication off; {local}"
    return session.get(ApiKey, given), f"no API key {given!r}{LISTED}"


def cancel_unfinished_jobs(session: Session, key: ApiKey) -> int:
    """Cancel a revoked key's queued and running jobs; how many. They had run on, holding workers for hours, with
    results no key can read and no request able to cancel them."""
    job_ids = list(session.scalars(select(Job.id).where(Job.owner_key_id == key.id,
                                                        Job.state.not_in(TERMINAL_STATES))))
    request_cancel(session=session, job_ids=job_ids)  # (the ending names the revoke: voxe_service.jobs.finish_jobs)
    return len(job_ids)


def fail_processing_scenes(session: Session, key: ApiKey) -> list[str]:
    """Fail a revoked key's scenes still processing, naming the revoke; their ids. Their ingests had still run,
    taking a worker for a scene no key can use or delete; a queued one now skips it, and a running one stops at its
    next step (``worker.ingest``), what it stored discarded."""
    scene_ids = list(session.scalars(select(Scene.id).where(Scene.owner_key_id == key.id, Scene.state == PROCESSING)))
    return [scene_id for scene_id in scene_ids
            if fail_scene(session, scene_id, f"its API key {key.id} was revoked while it was processing")]


def _expiry(key: ApiKey) -> str:
    """The key's expiry as it stands: an update-key changing an expired key's quotas had said "expires <a time
    past>", as if the key worked."""
    if key.expires_at is None:
        return "never expires"
    when = key.expires_at.isoformat(timespec="seconds")
    return f"expired {when}: its token is refused until --expires-in gives it a later expiry" if has_expired(key) \
        else f"expires {when}"


def _secret_reader(key: ApiKey) -> str:
    """Who reads a rotated webhook secret: "its holder reads it at GET /v1/webhooks/secret" had been said of a revoked
    or expired key too, whose token that answers 401 (rotating still serves: the deliveries left are signed with a
    secret the leaked one no longer forges)."""
    if key.revoked_at is not None:
        return ("which no one can read: the key is revoked (GET /v1/webhooks/secret answers its token 401), so its "
                "receivers refuse the deliveries still sent")
    if has_expired(key):
        return ("which its holder reads at GET /v1/webhooks/secret only once the key is given a later expiry "
                "(update-key --expires-in): it expired "
                f"{key.expires_at.isoformat(timespec='seconds')}")
    return "which its holder reads at GET /v1/webhooks/secret"


UPDATES = ("max_active_jobs", "max_upload_bytes", "expires_in")


def update_key(session: Session, key: ApiKey, changes: dict) -> str:
    """Apply ``changes`` (of :data:`UPDATES`; None: the setting's quota, or no expiry) to a key not revoked; what it
    holds now. Read again by each request, they hold from its next one: quotas had been fixed at creation, so a key
    outgrown or abused could only be revoked, its jobs canceled, and a new token handed out."""
    for name in ("max_active_jobs", "max_upload_bytes"):
        if name in changes:
            setattr(key, name, changes[name])
    if "expires_in" in changes:
        key.expires_at = None if changes["expires_in"] is None else utcnow() + changes["expires_in"]
    session.commit()
    return (f"max_active_jobs={key.max_active_jobs or 'default'}, max_upload_bytes={key.max_upload_bytes or 'default'}"
            f", {_expiry(key)}")


def main(argv: list[str] | None = None) -> int:
    """The command's exit status; a database that is down or unreachable said in a line (it had ended in SQLAlchemy's
    traceback, a page of it to read the cause out of), as is a setting refused (VOXE_DEVICE=gpu had ended in a
    traceback through get_settings)."""
    try:
        return _command(argv)
    except SettingsError as exc:
        return refuse_settings("python -m api.admin", exc)
    except DATABASE_UNAVAILABLE as exc:
        if (line := outage_line(exc)) is None:
            raise
        return refuse_settings("python -m api.admin", line)


def _command(argv: list[str] | None) -> int:
    parser = argparse.ArgumentParser(prog="python -m api.admin", description="Manage the Vox-E service's API keys.")
    commands = parser.add_subparsers(dest="command", required=True)
    create = commands.add_parser("create-key", help="create a key and print its token (shown only once)")
    create.add_argument("--name", required=True, help="who or what the key is for")
    create.add_argument("--max-active-jobs", type=_count_up_to(2**31 - 1), help="queued + running jobs (default: "
                        "VOXE_MAX_ACTIVE_JOBS_PER_KEY)")
    create.add_argument("--max-upload-bytes", type=_count_up_to(2**63 - 1), help="bytes of stored scenes (default: "
                        "VOXE_MAX_UPLOAD_BYTES_PER_KEY)")
    create.add_argument("--expires-in", type=_lifetime, help="refuse the key this long from now: a whole number of s, "
                        "m, h or d, e.g. 90d (default: it never expires)")
    commands.add_parser("list-keys", help="list keys (never their tokens)")
    update = commands.add_parser("update-key", help="change a key's quotas or expiry (its token stays the same)")
    update.add_argument("key_id", help="the key's id, or its token")
    update.add_argument("--max-active-jobs", type=_count_up_to(2**31 - 1, or_default=True),
                        default=argparse.SUPPRESS, help="queued + running jobs, or 'default' "
                        "(VOXE_MAX_ACTIVE_JOBS_PER_KEY)")
    update.add_argument("--max-upload-bytes", type=_count_up_to(2**63 - 1, or_default=True),
                        default=argparse.SUPPRESS, help="bytes of stored scenes, or 'default' "
                        "(VOXE_MAX_UPLOAD_BYTES_PER_KEY)")
    expiry = update.add_mutually_exclusive_group()
    expiry.add_argument("--expires-in", type=_lifetime, default=argparse.SUPPRESS,
                        help="refuse the key this long from now (an expired key works again until then)")
    expiry.add_argument("--never-expires", dest="expires_in", action="store_const", const=None,
                        default=argparse.SUPPRESS, help="the key no longer expires")
    rotate = commands.add_parser("rotate-webhook-secret", help="give a key a new webhook signing secret (the old "
                                 "one leaked): every delivery attempt from now on is signed with it")
    rotate.add_argument("key_id", help="the key's id ('local' with authentication off), or its token")
    revoke = commands.add_parser("revoke-key", help="revoke a key: its token stops working at once, its unfinished "
                                    "jobs are canceled and its scenes still processing failed")
    revoke.add_argument("key_id", help="the key's id, or its token (a leaked one, say)")
    args = parser.parse_args(argv)
    changes = {name: getattr(args, name) for name in UPDATES if hasattr(args, name)}
    if args.command == "update-key" and not changes:
        update.error("say what to change: --max-active-jobs, --max-upload-bytes, --expires-in or --never-expires")
    if args.command == "create-key" and (problem := name_problem(args.name.strip())) is not None:
        create.error(f"--name {problem}")  # a usage error (2) before the database: down, it had been said instead (1)

    run_migrations(get_settings().database_url)
    with session_scope() as session:
        if args.command == "create-key":
            expires_at = utcnow() + args.expires_in if args.expires_in else None
            key, token = create_key(session, args.name.strip(), args.max_active_jobs, args.max_upload_bytes,
                                    expires_at)
            print(f"created key {key.id} ({key.name}, {_expiry(key)}); its token, shown only this once:",
                  file=sys.stderr)
            print(token)
        elif args.command == "list-keys":
            for key in session.scalars(select(ApiKey).where(ApiKey.id != LOCAL_KEY_ID).order_by(ApiKey.created_at)):
                state = (f"revoked {key.revoked_at.isoformat()}" if key.revoked_at else
                         f"expired {key.expires_at.isoformat()}" if has_expired(key) else "active")
                print(f"{key.id}\t{key.name}\t{state}\tcreated {key.created_at.isoformat()}\t"
                      f"max_active_jobs={key.max_active_jobs or 'default'}\t"
                      f"max_upload_bytes={key.max_upload_bytes or 'default'}\t"
                      f"expires_at={key.expires_at.isoformat() if key.expires_at else 'never'}")
        elif args.command == "update-key":
            key, missing = key_named(session, args.key_id, local=(
                "its quotas are VOXE_MAX_ACTIVE_JOBS_PER_KEY and VOXE_MAX_UPLOAD_BYTES_PER_KEY, and it has no token "
                "to expire"))
            if key is None or key.revoked_at is not None:
                print(missing if key is None else f"API key {key.id} ({key.name}) was revoked at "
                      f"{key.revoked_at.isoformat(timespec='seconds')}: a revoked key stays so (create a new one)",
                      file=sys.stderr)
                return 1
            print(f"updated key {key.id} ({key.name}): {update_key(session, key, changes)}", file=sys.stderr)
        elif args.command == "rotate-webhook-secret":
            key, missing = key_named(session, args.key_id, local=None)
            if key is None:
                print(missing, file=sys.stderr)
                return 1
            rotate_webhook_secret(session=session, key=key)
            print(f"rotated the webhook secret of key {key.id} ({key.name}): every delivery attempt from now on, a "
                  f"retry of an earlier one included, is signed with the new one, {_secret_reader(key)}",
                  file=sys.stderr)
        else:
            key, missing = key_named(session, args.key_id)
            if key is None:
                print(missing, file=sys.stderr)
                return 1
            # A key revoked before is said to be, and since when ("revoked key" had read as though it was live until
            # now: the time a leaked key was cut off is what an incident's timeline needs).
            done = (f"revoked key {key.id} ({key.name})" if key.revoked_at is None else f"key {key.id} ({key.name}) "
                    f"was already revoked at {key.revoked_at.isoformat(timespec='seconds')}")
            if key.revoked_at is None:
                key.revoked_at = utcnow()
                session.commit()  # its token refused from here on, before its jobs are canceled
            canceled = cancel_unfinished_jobs(session, key)
            failed = fail_processing_scenes(session, key)
            session.commit()
            get_storage(get_settings()).discard_prefixes(*(scene_key(scene_id) for scene_id in failed))
            print(f"{done}; its {canceled} unfinished job(s) canceled (a running one stops at its next cancel check) "
                  f"and {len(failed)} scene(s) still processing failed", file=sys.stderr)
    return 0


if __name__ == "__main__":
    sys.exit(main())
