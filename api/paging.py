"""Paging of the listings, newest first: by ``offset``, or by the ``cursor`` a page's ``next_cursor`` gives.

A cursor names the last row's sort key (created_at, id), so the next page starts after that row wherever it now
stands: jobs added or deleted meanwhile had shifted an offset's page (an "older" page repeated rows, or skipped them).
The order is total (ties on created_at by id) and read off an index on (owner_key_id, created_at, id).
"""

from __future__ import annotations

import base64
import binascii
import json
import re
from collections.abc import Callable
from dataclasses import dataclass
from datetime import datetime, timezone
from typing import Annotated

from fastapi import HTTPException, Query, Request, status
from pydantic import BeforeValidator
from pydantic_core import PydanticCustomError
from sqlalchemy import func, select, true, tuple_
from sqlalchemy.orm import Session, join

from voxe_core.constants import INTEGER_AS_WRITTEN
from voxe_service.texts import listed

MAX_OFFSET = 1_000_000_000
MAX_CURSOR_LENGTH = 200
ROW_ID = re.compile(r"[0-9a-f]{32}")
"""The form of the rows' ids (voxe_service.models.new_id: uuid4().hex); a cursor's id of any other form is unreadable."""
LISTINGS: set[str] = set()
"""The listings :func:`page_query` reads cursors of: a cursor naming one of them may be named in a 422."""


def _digits_only(value):
    """A query integer as written: digits, an optional minus. Pydantic's lax reading of a string had taken 1_0 as
    10, +5 and " 5" as 5 (a + in a query is a space) and 5.0 as 5: a typo answered as though it were meant."""
    if isinstance(value, str) and not INTEGER_AS_WRITTEN.fullmatch(value):
        raise PydanticCustomError("int_parsing", "Input should be an integer written in the digits 0-9 (a leading - "
                                                 "allowed), nothing else")
    return value


DIGITS_ONLY = BeforeValidator(_digits_only)
"""Reads an integer query parameter strictly: ``Annotated[int, Query(...), DIGITS_ONLY] = default`` (after the
``Query``: before it, the document's bounds read ``ge``/``le`` for ``minimum``/``maximum``; with the ``Query`` as the
default, FastAPI drops it)."""


@dataclass(frozen=True)
class PageQuery:
    """What a listing request asks for: ``limit`` rows from ``offset``, or after the row ``after`` names."""

    limit: int
    offset: int
    after: tuple[datetime, str] | None


@dataclass(frozen=True)
class PageRows:
    """A page's rows, how many rows match, how many come before the page, and the cursor of the next (None: last)."""

    rows: list
    total: int
    offset: int
    next_cursor: str | None


def page_query(listing: str) -> Callable[..., PageQuery]:
    """The dependency reading ``limit``, ``offset`` and ``cursor`` of ``listing`` (its path, as a cursor names it)."""
    LISTINGS.add(listing)

    def read(request: Request,
             limit: Annotated[int, Query(ge=1, le=200), DIGITS_ONLY] = 20,
             offset: Annotated[int, Query(ge=0, le=MAX_OFFSET, description="rows to skip (a page shifts while rows "
                                          "are added: prefer `cursor`); not with `cursor`"), DIGITS_ONLY] = 0,
             cursor: str | None = Query(None, max_length=MAX_CURSOR_LENGTH,
                                        description="the `next_cursor` of the page before: the page after its last "
                                                    "row, however many rows were added or deleted since; not with "
                                                    "`offset`")) -> PageQuery:
        if cursor is None:
            return PageQuery(limit=limit, offset=offset, after=None)
        if "offset" in request.query_params:
            raise HTTPException(status.HTTP_422_UNPROCESSABLE_CONTENT,
                                "send either cursor or offset, not both: a cursor names where its page starts")
        return PageQuery(limit=limit, offset=0, after=decode_cursor(listing, cursor))

    return read


def encode_cursor(listing: str, row) -> str:
    """An opaque cursor naming ``row``'s place in ``listing``."""
    text = json.dumps([listing, row.created_at.isoformat(), row.id], separators=(",", ":"))
    return base64.urlsafe_b64encode(text.encode()).decode().rstrip("=")


def decode_cursor(listing: str, cursor: str) -> tuple[datetime, str]:
    """The (created_at, id) a cursor of ``listing`` names; 422 naming the cursor for any other text.

    The name and id are checked against what they can be before use: a crafted cursor's lone surrogate or NUL had
    failed the 422's encoding, or the database's, as a 500."""
    try:
        name, created_at, row_id = json.loads(base64.urlsafe_b64decode(cursor + "=" * (-len(cursor) % 4)))
        when = datetime.fromisoformat(created_at)
        readable = (name in LISTINGS and isinstance(row_id, str) and ROW_ID.fullmatch(row_id) is not None
                    and when.tzinfo is not None)
        when = when.astimezone(timezone.utc) if readable else when  # (SQLite compares the stored UTC wall time)
    except (ValueError, TypeError, OverflowError, binascii.Error):
        readable = False
    if not readable:
        raise HTTPException(status.HTTP_422_UNPROCESSABLE_CONTENT,
                            f"cursor {listed([cursor])} is not a cursor of GET {listing}: send a page's next_cursor "
                            "unchanged")
    if name != listing:
        raise HTTPException(status.HTTP_422_UNPROCESSABLE_CONTENT,
                            f"cursor {listed([cursor])} is a cursor of GET {name}, not of GET {listing}")
    return when, row_id


def read_page(session: Session, listing: str, model, filters: list, page: PageQuery) -> PageRows:
    """The page of ``model`` rows matching ``filters``, newest first (ties: the larger id first).

    The total, the page's offset and its rows come from one statement, so from one snapshot of the table: counted
    apart, a row created between the statements had shifted an offset's page by one against its total, and given a
    cursor's page an offset past the total ("4–4 of 3"). The counts are the statement's first table, the page joined
    to it, so a page past the end is still one row: the counts, with no page row. The page is chosen by its ids (the
    listing's index holds them) and its rows joined to those, so the statement is ordered by the model's own columns:
    ordered by an aliased page's, each call had adapted them to it, three times the two statements' Python time."""
    place = tuple_(model.created_at, model.id)
    counts = [func.count().label("total")]
    chosen = select(model.id).where(*filters).order_by(model.created_at.desc(), model.id.desc())
    if page.after is None:
        chosen = chosen.offset(page.offset)
    else:
        counts.append(func.count().filter(place >= page.after).label("before"))
        chosen = chosen.where(place < page.after)
    counted = select(*counts).select_from(model).where(*filters).subquery("counts")
    chosen = chosen.limit(page.limit + 1).subquery("page")  # (one past the page: is there a next one?)
    page_rows = join(model, chosen, model.id == chosen.c.id)
    found = session.execute(select(counted, model).select_from(counted.outerjoin(page_rows, true()))
                            .order_by(model.created_at.desc(), model.id.desc())).all()
    total, offset = found[0].total, (page.offset if page.after is None else found[0].before)
    rows = [found_row[-1] for found_row in found if found_row[-1] is not None]
    more = len(rows) > page.limit
    rows = rows[:page.limit]
    return PageRows(rows=rows, total=total, offset=offset,
                    next_cursor=encode_cursor(listing, rows[-1]) if more else None)
