"""Scene uploads: unpack into a staging folder, check what is cheap to check, pack it for storage.

Everything answered here is answered at once (4xx) and leaves nothing behind: the caller
stores the packed archive and inserts the scene row only after :func:`stage_upload`
returns, and the staging folder is always removed (:func:`staging_folder`; one that an API
process killed mid-upload left, by :func:`sweep_staging` as an API process starts). What
only decoding every image (or loading and rendering a mesh) can find is the worker's ingest
(``worker/ingest.py``): the scene is ``processing`` until it is ``ready``, or ``failed`` with the reason.

Hostile archives: entries with ``..``, absolute or drive paths, symbolic links or
encryption, a central directory of more records (or bytes) than ``max_upload_files`` files
explain (counted before ``zipfile`` builds an object per record), more than
``max_upload_files`` files, more than ``max_extracted_bytes`` of content, or an entry, or
the entries so far together, inflating more than ``max_compression_ratio`` times the
compressed bytes read for them are refused. Sizes and ratios are counted while
extracting, from the bytes actually read and written, never from the archive's
directory. Images are checked against ``max_image_pixels`` from their headers
before any is decoded (decompression bombs).

Datasets (NeRF-synthetic, instant-ngp / nerfstudio ``transforms.json``, a COLMAP model
``sparse/0/`` or ``sparse/`` ``cameras|images.bin|txt`` beside ``images/``): ``voxe_core.data.load_scene`` checks
the cameras with only the first image decoded (frames, poses, intrinsics, lens distortion,
paths inside the upload); then every frame's image must exist and have a readable header
of the first image's size.

Meshes: an upload with no transforms json but one ``.obj`` or ``.ply`` (with at most one texture
image; beside a PLY, only where its header declares texture coordinates) is packed under ``mesh/``
(``voxe_service.datasets``); the ingest loads it and renders it into a NeRF-synthetic dataset (mesh input route (a)),
kept for route (b), and the scene's format is ``mesh``.
"""

from __future__ import annotations

import json
import logging
import lzma
import os
import re
import shutil
import stat
import struct
import uuid
import warnings
import zipfile
import zlib
from contextlib import AbstractContextManager
from dataclasses import dataclass
from pathlib import Path, PurePosixPath
from typing import BinaryIO

from PIL import Image

from api.http_semantics import ID_SHOWN
from voxe_core.data import (DatasetError, colmap_transforms, detect_format, find_image, image_candidates,
                            image_not_found, is_dataset_folder, load_scene, quarter_turn_hint)
from voxe_core.constants import TEXTURE_SUFFIXES
from voxe_core.mesh_input import (DECIMATE, MAX_MESH_FACES, MESH_FRAMES, MESH_INPUT_SUFFIXES,
                                   referenced_base_name)
from voxe_core.ply_header import ply_fault, read_ply_header
from voxe_service import datasets
from voxe_service.datasets import (DATASET_ARCHIVE, MESH_FOLDER, MESH_FORMAT, MESH_NAMES, MESH_OPTIONS, UPLOAD_ARCHIVE,
                                   ignored, package)
from voxe_service.scratch import locked_folder, sweep_unlocked
from voxe_service.settings import SettingsError
from voxe_service.texts import listed

log = logging.getLogger("voxe.api")
_RATIO_FLOOR = 4 << 20  # below this many bytes out of an entry (or the archive), any ratio is fine (text compresses)
# Small reads: zipfile reads ahead as many compressed bytes as were asked for, and with a lying directory
# (an entry claiming more compressed bytes than its stream has) that read-ahead would pad the ratio's divisor.
_CHUNK = 64 << 10
# A zip's directory may list this many records per file VOXE_MAX_UPLOAD_FILES allows: the file, its folder's entry
# and macOS's __MACOSX/._ copies of both; each record taking at most this many bytes (46 fixed, then its name and
# extra fields: a few hundred in any real archive).
_ENTRIES_PER_FILE = 4
_ENTRIES_SLACK = 8  # the top folder (and its __MACOSX twin) of a Finder zip of exactly the allowed files: 4N + 2
_DIRECTORY_BYTES_PER_ENTRY = 1024
_UPLOADS, _STAGING_PREFIX = "uploads", "upload-"  # work_dir/uploads/upload-*
_CENTRAL_RECORD = struct.Struct("<4s24x3H12x")  # signature, then the name, extra and comment lengths (46 bytes)
_END_RECORD = struct.Struct("<4s8xL6x")  # signature, then the directory's size (22 bytes, then a comment)
_ZIP64_LOCATOR_SIGNATURE = b"PK\x06\x07"  # 20 bytes, right before the end record
_ZIP64_END_RECORD = struct.Struct("<4s36xQ8x")  # signature, then the directory's size (56 bytes, before the locator)
_MAX_ZIP_COMMENT = 0xFFFF


class UploadError(ValueError):
    """A bad upload; ``status`` is the HTTP status to answer with (422, or 413 for size limits)."""

    def __init__(self, message: str, status: int = 422):
        super().__init__(message)
        self.status = status


def _archive_named(name: str | None) -> str:
    """The uploaded zip as a message names it: "archive 'bad.zip'" (its file name as sent), or "archive" when it
    came without one."""
    return f"archive {listed([name], width=ID_SHOWN)}" if name else "archive"


def _directory_extent(source: BinaryIO, archive: str = "archive") -> tuple[int, int]:
    """(where a zip's central directory starts, its size in bytes): it ends where the end records begin (zip64's
    end record when its locator precedes the end record), so data before the archive (a self-extractor) does not
    matter. The end record is found as zipfile finds it: the file's last 22 bytes, else the last signature within
    a comment's reach. UploadError (422, naming ``archive``: :func:`_archive_named`) when there is none."""
    length = source.seek(0, os.SEEK_END)
    tail_size = min(length, _END_RECORD.size)
    source.seek(length - tail_size)
    tail = source.read(tail_size)
    plain = len(tail) == _END_RECORD.size and tail[:4] == zipfile.stringEndArchive and tail[-2:] == b"\0\0"
    if not plain:  # a comment follows the end record: its signature within the comment's longest reach
        tail_size = min(length, _END_RECORD.size + _MAX_ZIP_COMMENT)
        source.seek(length - tail_size)
        tail = source.read(tail_size)
    at = 0 if plain else tail.rfind(zipfile.stringEndArchive)
    if at < 0 or len(tail) - at < _END_RECORD.size:
        raise UploadError(f"{archive} is not a readable zip file: no end of central directory record")
    end, size = length - tail_size + at, _END_RECORD.unpack_from(tail, at)[1]
    zip64_at = end - 20 - _ZIP64_END_RECORD.size
    if zip64_at >= 0:
        source.seek(zip64_at)
        records = source.read(_ZIP64_END_RECORD.size + 4)
        if records[-4:] == _ZIP64_LOCATOR_SIGNATURE and records[:4] == zipfile.stringEndArchive64:
            end, size = zip64_at, _ZIP64_END_RECORD.unpack(records[:_ZIP64_END_RECORD.size])[1]
    return end - size, size


@dataclass
class StagedUpload:
    """An upload that passed the cheap checks, packed for storage (``archive_name`` under the scene's prefix)."""

    format: str
    image_count: int
    width: int
    height: int
    splits: list[str]
    archive: Path
    archive_name: str


def safe_relative(name: str) -> PurePosixPath:
    """The relative path of an archive entry or uploaded file name; UploadError on anything escaping."""
    raw = name.replace("\\", "/")
    refused = f"refused entry {listed([name], width=ID_SHOWN)}"  # (a zip's name may hold 64 kB)
    if raw.startswith("/") or re.match(r"^[A-Za-z]:", raw):
        raise UploadError(f"{refused}: absolute paths are not allowed")
    parts = [p for p in raw.split("/") if p not in ("", ".")]
    if any(p == ".." for p in parts):
        raise UploadError(f"{refused}: '..' path components are not allowed")
    if not parts:
        raise UploadError(f"{refused}: empty path")
    if any("\x00" in p for p in parts):
        raise UploadError(f"{refused}: NUL in path")
    return PurePosixPath(*parts)


def too_many_files(max_files: int) -> str:
    return f"too many files: more than {max_files} (VOXE_MAX_UPLOAD_FILES)"


class _Budget:
    def __init__(self, max_bytes: int, max_files: int, max_ratio: float):
        self.max_bytes, self.max_files, self.max_ratio = max_bytes, max_files, max_ratio
        self.bytes = self.files = 0
        self.compressed = 0  # compressed bytes the entries extracted so far were read from

    def add_file(self) -> None:
        self.files += 1
        if self.files > self.max_files:
            raise UploadError(too_many_files(self.max_files), 413)

    def check_directory(self, source: BinaryIO, archive: str = "archive") -> None:
        """413 for a zip whose central directory holds more records (or bytes) than ``max_files`` files explain.

        ``zipfile.ZipFile`` reads the whole directory and builds an object per record before any file can be
        counted (a 47 MB directory of a million empty entries took 314 MiB): the records are counted here first,
        one at a time, where the end records (zip64's too) say they are, and whatever their count claims. The
        end records are read here, as zipfile finds them, rather than through zipfile's private reader, whose
        results changed meaning between Python releases (gh-139700). A directory that is not where they say is
        the 422 zipfile would give, naming ``archive`` (:func:`_archive_named`).
        """
        most = _ENTRIES_PER_FILE * self.max_files + _ENTRIES_SLACK
        start, size = _directory_extent(source, archive)
        if size > most * _DIRECTORY_BYTES_PER_ENTRY:
            raise UploadError(f"the directory of {archive} takes {size} bytes, more than {_DIRECTORY_BYTES_PER_ENTRY} "
                              f"per entry for the {most} entries VOXE_MAX_UPLOAD_FILES={self.max_files} allows", 413)
        position = entries = 0
        while position < size:
            source.seek(start + position)
            record = source.read(_CENTRAL_RECORD.size)
            if len(record) < _CENTRAL_RECORD.size or record[:4] != zipfile.stringCentralDir:
                raise UploadError(f"{archive} is not a readable zip file: its central directory is not where its "
                                  "end record says")
            _, name, extra, comment = _CENTRAL_RECORD.unpack(record)
            position += _CENTRAL_RECORD.size + name + extra + comment
            entries += 1
            if entries > most:
                raise UploadError(f"too many files: the directory of {archive} lists more than {most} entries "
                                  f"({_ENTRIES_PER_FILE} per file of VOXE_MAX_UPLOAD_FILES={self.max_files}: files, "
                                  "folders and macOS's __MACOSX copies)", 413)

    def add_bytes(self, n: int) -> None:
        self.bytes += n
        if self.bytes > self.max_bytes:
            raise UploadError(f"upload too large: more than {self.max_bytes} bytes of content "
                              "(VOXE_MAX_EXTRACTED_BYTES)", 413)

    def check_ratio(self, name: str, written: int, compressed: int, archive: str = "archive") -> None:
        """The entry's ratio (``written`` from ``compressed``), and the archive's over every entry so far: many
        entries each under the floor had written 256 MiB from a 267 kB upload. ``archive`` names the zip
        (:func:`_archive_named`)."""
        if written > _RATIO_FLOOR and written > self.max_ratio * max(compressed, 1):
            raise UploadError(f"refused entry {listed([name], width=ID_SHOWN)}: it inflates more than "
                              f"{self.max_ratio:g} times the {compressed} compressed bytes read so far (a zip bomb?; "
                              "VOXE_MAX_COMPRESSION_RATIO)", 413)
        read = self.compressed + compressed
        if self.bytes > _RATIO_FLOOR and self.bytes > self.max_ratio * max(read, 1):
            raise UploadError(f"refused {archive}: its entries inflate more than {self.max_ratio:g} times the {read} "
                              "compressed bytes read so far (a zip bomb?; VOXE_MAX_COMPRESSION_RATIO)", 413)


class _CountingReader:
    """A seekable file that counts the bytes read from it: what a zip entry really consumed."""

    def __init__(self, raw: BinaryIO):
        self.raw, self.consumed = raw, 0

    def read(self, n: int = -1) -> bytes:
        data = self.raw.read(n)
        self.consumed += len(data)
        return data

    def seek(self, offset: int, whence: int = 0) -> int:
        return self.raw.seek(offset, whence)

    def tell(self) -> int:
        return self.raw.tell()

    def seekable(self) -> bool:
        return True


def _copy(src: BinaryIO, dest: Path, budget: _Budget, consumed=None, name: str = "", archive: str = "archive") -> None:
    """Stream ``src`` into a new file, charging the budget; ``consumed()`` (compressed bytes read so far)
    bounds the inflation ratio (of entry ``name`` in the zip ``archive`` names)."""
    dest.parent.mkdir(parents=True, exist_ok=True)
    written = 0
    with open(dest, "xb") as out:
        while chunk := src.read(_CHUNK):
            budget.add_bytes(len(chunk))
            written += len(chunk)
            if consumed is not None:
                budget.check_ratio(name, written, consumed(), archive)
            out.write(chunk)


_JAPANESE = "\u3000-\u30ff\u4e00-\u9fff\uff01-\uff9f"  # CJK punctuation, kana, ideographs, full- and half-width forms
_JAPANESE_NAME = re.compile(f"[\\x00-\\x7f{_JAPANESE}]*")
_KANA_OR_KANJI_RUN = re.compile("[\u3041-\u30ff\u4e00-\u9fff]{2}")  # (a cp437 "étés" reads as full-width "ＵＴ")


def _legacy_bytes(info: zipfile.ZipInfo) -> bytes | None:
    """The bytes of an entry's name stored without the zip UTF-8 flag (0x800) that are not UTF-8 (zipfile decoded
    them as cp437); None for any other name (flagged, UTF-8, or one zipfile took from a Unicode path field)."""
    if info.flag_bits & 0x800:
        return None
    try:
        raw = info.filename.encode("cp437")
        raw.decode("utf-8")
    except UnicodeEncodeError:
        return None
    except UnicodeDecodeError:
        return raw
    return None


def _legacy_encoding(infos: list[zipfile.ZipInfo]) -> str:
    """How the archive's names without the UTF-8 flag that are not UTF-8 are read: as Shift-JIS (cp932: Japanese
    Windows' Explorer and older zip tools; zipfile read "画像_0.png" as "ëµæ£_0.png", its frame "not found") where every
    one of them reads so as ASCII and Japanese script and one holds two kana or kanji in a row; else as cp437,
    the zip format's own, as zipfile reads them. An archive is written in one encoding, and a Western cp437 name read
    as Shift-JIS makes single characters apart ("crème" as "cr確e"): the run of two tells them apart."""
    names = []
    for info in infos:
        if (raw := _legacy_bytes(info)) is not None:
            try:
                names.append(raw.decode("cp932"))
            except UnicodeDecodeError:
                return "cp437"
    japanese = all(_JAPANESE_NAME.fullmatch(name) for name in names) and any(map(_KANA_OR_KANJI_RUN.search, names))
    return "cp932" if japanese else "cp437"


def _entry_name(info: zipfile.ZipInfo, encoding: str = "cp437") -> str:
    """The entry's name. Info-ZIP's ``zip`` (Linux, macOS) stores UTF-8 names without the zip UTF-8 flag (0x800),
    which zipfile then decodes as cp437 ("café_0.png" as "caf├⌐_0.png": its frame "not found"); such a name whose
    bytes are valid UTF-8 is read as UTF-8, another in the archive's ``encoding`` (:func:`_legacy_encoding`)."""
    if (raw := _legacy_bytes(info)) is not None:
        return raw.decode(encoding)
    if info.flag_bits & 0x800:
        return info.filename
    try:
        return info.filename.encode("cp437").decode("utf-8")
    except UnicodeError:  # a name zipfile took from a Unicode path field
        return info.filename


def _is_folder(info: zipfile.ZipInfo) -> bool:
    """Whether a zip entry is a folder: zipfile knows one by its trailing "/" only, where a folder may end in "\\"
    (.NET Framework's ZipFile named entries with backslashes) or, holding nothing, be marked by its attributes alone
    (MS-DOS's directory bit, a Unix S_IFDIR mode). Extracted as empty files, such folders had made their files' entries
    "collide with another entry's path"."""
    marked = info.external_attr & 0x10 or stat.S_ISDIR(info.external_attr >> 16)
    return info.is_dir() or info.filename.endswith("\\") or (info.file_size == 0 and bool(marked))


def extract_zip(source: BinaryIO, dest: Path, budget: _Budget, name: str | None = None) -> None:
    """Check every entry's name and type first, then stream the entries out under the budget. A zip that is none, or
    one past a limit, is refused naming its file ``name`` (as sent), as a file sent loose is named: the 422 had said
    only "archive is not a readable zip file", the 413s "the archive's directory" or "refused archive"."""
    label = _archive_named(name)
    budget.check_directory(source, label)
    reader = _CountingReader(source)
    try:
        archive = zipfile.ZipFile(reader)
    except (zipfile.BadZipFile, OSError, ValueError, EOFError) as exc:
        raise UploadError(f"{label} is not a readable zip file: {exc}") from None
    with archive:
        entries, seen, encoding = [], {}, _legacy_encoding(archive.infolist())
        for info in archive.infolist():
            info.filename = _entry_name(info, encoding)  # (zipfile checks the local header against ``orig_filename``)
            path, entry = safe_relative(info.filename), listed([info.filename], width=ID_SHOWN)
            if stat.S_ISLNK(info.external_attr >> 16):
                raise UploadError(f"refused entry {entry}: symbolic links are not allowed")
            if _is_folder(info) or ignored(path):
                continue
            if info.flag_bits & 0x1:
                raise UploadError(f"refused entry {entry}: encrypted zip entries are not supported")
            if path in seen:
                raise UploadError(f"duplicate entry {entry} in the archive (same path as {seen[path]})")
            seen[path] = entry
            budget.add_file()
            entries.append((info, path))
        for info, path in entries:
            entry = listed([info.filename], width=ID_SHOWN)
            try:
                start = reader.consumed
                with archive.open(info) as member:
                    _copy(member, dest / path, budget, lambda: reader.consumed - start, info.filename, label)
                budget.compressed += reader.consumed - start
            except UploadError:
                raise
            except FileExistsError:
                raise UploadError(f"entry {entry} collides with another entry's path") from None
            except (zlib.error, lzma.LZMAError) as exc:  # (a damaged stream: neither is an OSError, a 500 had been)
                raise UploadError(f"cannot extract {entry}: its compressed data is damaged ({exc})") from None
            except OSError as exc:  # its text names the staging folder's path on this machine: its reason alone
                raise UploadError(f"cannot extract {entry}: {exc.strerror or exc}") from None
            except (zipfile.BadZipFile, zipfile.LargeZipFile, EOFError, NotImplementedError, ValueError,
                    RuntimeError) as exc:
                raise UploadError(f"cannot extract {entry}: {exc}") from None


def save_files(files: list[tuple[str, BinaryIO]], dest: Path, budget: _Budget) -> None:
    """Individual uploaded files; their names are paths relative to the dataset folder."""
    for name, handle in files:
        path = safe_relative(name or "")
        if ignored(path):
            continue
        budget.add_file()
        shown = listed([name], width=ID_SHOWN)
        try:
            _copy(handle, dest / path, budget)
        except FileExistsError:
            raise UploadError(f"file {shown} uploaded twice (or collides with another file's path)") from None
        except OSError as exc:
            raise UploadError(f"cannot store file {shown}: {exc.strerror or exc}") from None


def dataset_root(folder: Path) -> Path:
    """The dataset folder (transforms json or COLMAP model): the upload itself, or its single top-level folder."""
    root = folder
    for _ in range(4):
        if is_dataset_folder(root):
            return root
        children = [c for c in root.iterdir() if not ignored(PurePosixPath(c.name))]
        if len(children) == 1 and children[0].is_dir():
            root = children[0]
            continue
        break
    return root


_FACE_LINE = re.compile(rb"\nf[ \t]([^\n]*)")  # an OBJ's face line (after its newline): "f", a space or tab, corners


def _obj_triangles(path: Path, bound: int) -> int:
    """How many triangles the face lines of the OBJ at ``path`` load as (a polygon of N corners is N - 2, a line at
    least one), read a megabyte at a time and counted only until past ``bound``. Lines continued by a backslash are
    joined first, as the loader joins them (a polygon of one corner a line had counted as one triangle). A line still
    open at a megabyte's end is carried over as its corners counted and the first byte of its last, maybe unfinished,
    word (carrying the whole word had made one long word cost time quadratic in its length)."""
    count, carried, open_corners = 0, b"\n", 0  # (a line's start: the file's, or the newline ending the line before)
    held = b""  # a continuation's backslash (and CR) the megabyte ended after, joined with the next one

    def triangles(face_lines: bytes) -> int:
        total = 0
        for match in _FACE_LINE.finditer(face_lines):
            corners = len(match[1].split()) + (open_corners if match.start() == 0 else 0)
            total += max(corners - 2, 1)
        return total

    with open(path, "rb") as handle:
        while count <= bound and (chunk := handle.read(1 << 20)):
            chunk = held + chunk
            kept = len(chunk) - (2 if chunk.endswith(b"\\\r") else 1 if chunk.endswith(b"\\") else 0)
            chunk, held = chunk[:kept], chunk[kept:]
            text = carried + chunk.replace(b"\\\r\n", b"").replace(b"\\\n", b"")
            end = text.rfind(b"\n")
            count += triangles(text[:end])
            if end > 0:
                open_corners = 0
            carried = text[end:]
            if (line := _FACE_LINE.match(carried)) and not carried[-1:].isspace():  # its last word may go on
                words = line[1].split()
                open_corners += len(words) - 1
                carried = b"\nf " + words[-1][:1]
            elif line:
                open_corners += len(line[1].split())
                carried = b"\nf "
            elif len(carried) > 2:  # no face line: the rest of it does not count
                carried = b"\n#"
    return count + triangles(carried + held) if count <= bound else count


OTHER_TEXTURE_SUFFIXES = (".bmp", ".dds", ".exr", ".gif", ".hdr", ".jp2", ".ktx", ".ktx2", ".psd", ".tga", ".tif",
                          ".tiff", ".webp")
"""Texture image kinds 3D tools write that the mesh loader does not read (it reads ``TEXTURE_SUFFIXES``): beside an
OBJ or a PLY, one is a 422, where it had been dropped and the mesh arrived without its colours. Other files beside a
mesh (a licence, a scan's data) are no texture and stay ignored."""


def _mtllib_name(obj: Path) -> str | None:
    """The material library the OBJ names as the loader (trimesh) reads it: the rest of the line after the first
    "mtllib" in its text, wherever it stands; None where there is none. (Read by its lines' keyword, an OBJ beginning
    with a byte order mark had named none.)"""
    with open(obj, "rb") as handle:
        text = b""
        while (at := text.find(b"mtllib")) < 0 and (chunk := handle.read(1 << 20)):
            text = text[-5:] + chunk
        if at < 0:
            return None
        text = text[at + 6:]
        while b"\n" not in text and (chunk := handle.read(1 << 20)):
            text += chunk
    return text.split(b"\n", 1)[0].decode("utf-8", "replace").strip()


def pack_mesh_upload(root: Path, dest: Path, shading: str = "auto", up_axis: str = "y") -> Path | None:
    """The upload's mesh (and texture, and material library) copied to ``dest/mesh/`` with its ``shading`` and
    ``up_axis`` options for the ingest, or None when it is not a mesh.

    The file rules are checked here: one mesh of at most ``MAX_MESH_FACES`` triangles (an OBJ's face lines', a PLY's
    header's faces; else a 413), a PLY's header as the loader reads it (``ply_fault``'s header faults; else a 422), at
    most one texture image (an OBJ's or a PLY's: the ingest's ``load_mesh`` samples it at the file's texture
    coordinates, which a PLY with an image must declare) and for an OBJ at most one .mtl. The texture is kept as
    ``texture.<ext>``, whatever the OBJ's .mtl or the PLY's TextureFile comment call it. The .mtl keeps its file name,
    which the OBJ's ``mtllib`` names: the loader looks it up (or its base name, in any case) inside the mesh's folder
    only, so an .mtl under another name, or beside an OBJ with no ``mtllib`` (sent without a texture), is a 422. A dataset folder is no mesh even with a mesh in it (COLMAP's fused.ply, say).
    """
    if is_dataset_folder(root):
        return None
    files = sorted(p for p in root.rglob("*") if p.is_file() and not ignored(PurePosixPath(p.name)))
    meshes = [p for p in files if p.suffix.lower() in MESH_INPUT_SUFFIXES]
    if not meshes:
        return None
    names = lambda paths: listed([p.relative_to(root).as_posix() for p in paths], width=ID_SHOWN)  # noqa: E731
    if len(meshes) > 1:
        raise UploadError(f"the upload holds several meshes ({names(meshes)}); send one")
    mesh, library = meshes[0], None
    kind = mesh.suffix.lower()[1:].upper()
    images = [p for p in files if p.suffix.lower() in TEXTURE_SUFFIXES]
    unread = [p for p in files if p.suffix.lower() in OTHER_TEXTURE_SUFFIXES]
    if kind == "PLY" and (fault := ply_fault(mesh, read_body=False)):  # (its body's: the ingest's load names them)
        raise UploadError(f"{mesh.name}: {fault}")
    header = read_ply_header(mesh) if kind == "PLY" else None
    # A PLY's faces as its header counts them (its polygons' corners are not summed: a binary body's would be read
    # whole; the ingest's load_mesh refuses a mesh loading as more triangles), an OBJ's triangles from its face lines
    faces = (header.faces or 0) if kind == "PLY" else _obj_triangles(mesh, MAX_MESH_FACES)
    if faces > MAX_MESH_FACES:
        counted = f" declares {faces:,} faces" if kind == "PLY" else f"'s face lines make {faces:,} triangles or more"
        raise UploadError(f"the {kind}{counted}, more than the {MAX_MESH_FACES:,} a mesh upload may hold: {DECIMATE} "
                          "and send it again", 413)
    if header and header.complete and not header.declares_texture_coordinates and images + unread:  # dropped
        raise UploadError(f"the PLY comes with {'an image' if len(images + unread) == 1 else 'images'} "
                          f"({names(images + unread)}) but its header declares no "
                          "texture coordinates (texcoord per face, or s t / u v / texture_u texture_v per vertex) to "
                          "map it with; send the image with a PLY that has them, or the PLY alone (its vertex or "
                          "face colours)")
    if unread:  # a texture the loader does not read had been dropped, the mesh arriving grey
        raise UploadError(f"the {kind} comes with an image of a kind not read as a texture ({names(unread)}); send "
                          f"its texture as {', '.join(TEXTURE_SUFFIXES)}")
    if len(images) > 1:
        raise UploadError(f"the {kind} comes with several images ({names(images)}); send one texture")
    texture = (images or [None])[0]
    if kind == "OBJ":
        libraries = [p for p in files if p.suffix.lower() == ".mtl"]  # its Kd colours, where no texture is sent
        if len(libraries) > 1:
            raise UploadError(f"the OBJ comes with several material libraries ({names(libraries)}); send one .mtl")
        library = (libraries or [None])[0]
        checked = library is not None and texture is None  # (beside a texture, the .mtl is not read)
        named = _mtllib_name(mesh) if checked else None
        if checked and not named:
            raise UploadError(f"the upload's material library is {names([library])}, but the OBJ has no mtllib line "
                              "naming one: the loader would not read it, and the mesh would load grey; write "
                              f"'mtllib {library.name}' in the OBJ, or send it without the .mtl")
        if checked and library.name.lower() != referenced_base_name(named):
            raise UploadError(f"the OBJ's mtllib names the material library {named!r}, but the upload's is "
                              f"{names([library])}: the loader would not find it, and the mesh would load grey; "
                              f"rename the .mtl to {referenced_base_name(named)!r}, or write "
                              f"'mtllib {library.name}' in the OBJ")
    kept_as = {mesh: f"mesh{mesh.suffix.lower()}"}
    if texture is not None:
        kept_as[texture] = f"texture{texture.suffix.lower()}"
    if library is not None:
        kept_as[library] = library.name  # as the OBJ's mtllib names it
    kept = dest / MESH_FOLDER
    kept.mkdir(parents=True)
    names = {}
    for source, stored in kept_as.items():
        shutil.copyfile(source, kept / stored)
        names[stored] = source.relative_to(root).as_posix()
    (kept / MESH_NAMES).write_text(json.dumps(names))  # the ingest's messages name the files as uploaded
    (kept / MESH_OPTIONS).write_text(json.dumps({"shading": shading, "up_axis": up_axis, "frame": MESH_FRAMES[-1]}))
    return dest


def check_image_pixels(folder: Path, max_pixels: int) -> None:
    """413 for any image whose header declares more than ``max_pixels`` pixels (nothing is decoded)."""
    for path in sorted(folder.rglob("*")):
        if not path.is_file():
            continue
        name = path.relative_to(folder).as_posix()
        try:
            with warnings.catch_warnings():
                warnings.simplefilter("ignore", Image.DecompressionBombWarning)
                with Image.open(path) as image:
                    width, height = image.size
        except Image.DecompressionBombError:
            width = height = None
        except MemoryError:
            raise
        except Exception:  # Pillow's plugins raise many kinds on odd headers (NotImplementedError for DDS's)
            continue  # not an image (the json, a readme); the loader reports referenced images it cannot read
        if width is None or width * height > max_pixels:
            size = f"{width}x{height} ({width * height} pixels)" if width is not None else "huge"
            raise UploadError(f"image {listed([name], width=ID_SHOWN)} is {size}, over the limit of {max_pixels} "
                              "pixels per image (a decompression bomb?; VOXE_MAX_IMAGE_PIXELS)", 413)


def _relative_message(message: str, staging: Path) -> str:
    """A message with staging paths shown relative to the upload."""
    for prefix in sorted({str(staging.resolve()), str(staging)}, key=len, reverse=True):
        message = message.replace(prefix + os.sep, "").replace(prefix, "<upload>")
    return message


def _invalid(message: str, staging: Path) -> UploadError:
    return UploadError(f"invalid dataset: {_relative_message(message, staging)}")


def check_dataset(root: Path, staging: Path, downsample: int) -> tuple[str, int, int, int, list[str]]:
    """(format, images, width, height, splits) of a dataset folder, from its json and its images' headers.

    ``load_scene`` with ``max_images=1`` checks every frame's entry and pose but decodes one image. An upload that
    is no dataset (nor a mesh, which ``pack_mesh_upload`` took) is a 422 naming what it holds and what is read.
    """
    if not is_dataset_folder(root):
        held = sorted(p.relative_to(root).as_posix() for p in root.rglob("*") if p.is_file())
        listing = listed(held, width=ID_SHOWN)
        raise UploadError(f"the upload is neither a dataset nor a mesh (it holds {listing or 'no file'}): send a "
                          "dataset folder or .zip (transforms_train.json: NeRF-synthetic; transforms.json: instant-ngp "
                          "/ nerfstudio; a COLMAP model sparse/0/ or sparse/ beside images/), or one mesh (.obj, .ply)")
    files = sum(1 for p in root.rglob("*") if p.is_file())  # the most frames that can each have an image
    try:
        fmt = detect_format(root)
        try:
            load_scene(root, "train", downsample=downsample, max_images=1, confine_paths=True, pixels=False,
                       max_frames=files)
        except DatasetError as exc:
            if "smaller than downsample" not in str(exc):
                raise
            load_scene(root, "train", downsample=1, max_images=1, confine_paths=True, pixels=False,
                       max_frames=files)
        if fmt == "colmap":
            json_path, meta = colmap_transforms(root)
        else:
            json_path = root / ("transforms_train.json" if fmt == "nerf_synthetic" else "transforms.json")
            meta = json.loads(json_path.read_bytes())  # parsed and checked by load_scene
    except DatasetError as exc:
        raise _invalid(str(exc), staging) from None
    frames = meta["frames"]
    width, height = _check_frame_images(root, json_path.relative_to(root).as_posix(), frames, staging)
    if fmt == "nerf_synthetic":
        splits = ["train"] + [s for s in ("val", "test") if _split_loads(root, s, files)]
    else:
        splits = ["all"]
    return fmt, len(frames), width, height, splits


def _split_loads(root: Path, split: str, files: int) -> bool:
    """Whether the NeRF-synthetic dataset's ``transforms_<split>.json`` loads (its first image decoded): one that does
    not (damaged, naming images not sent) had been listed in the scene's splits all the same. Jobs fit the train split
    alone, so such a file is left unlisted, not refused."""
    if not (root / f"transforms_{split}.json").is_file():
        return False
    try:
        load_scene(root, split, max_images=1, confine_paths=True, pixels=False, max_frames=files)
    except DatasetError:
        return False
    return True


_HEIF = re.compile(rb"(?s).{4}ftyp(hei[cmsx]|hev[cmsx]|mif1|msf1)")  # its file type box: size, "ftyp", brand


def heif_brand(path: Path) -> str | None:
    """The brand of a HEIF file, which Pillow does not read (an iPhone's photo: 'heic'); None for another file. Such
    a photo had been refused as "not an image or damaged"."""
    with open(path, "rb") as handle:
        match = _HEIF.match(handle.read(12))
    return match[1].decode() if match else None


def _check_frame_images(root: Path, json_name: str, frames: list[dict], staging: Path) -> tuple[int, int]:
    """Every frame's image exists with a readable header, all of one size (as the loader names them); that size."""
    first = None
    for i, frame in enumerate(frames):
        file_path = frame["file_path"]
        where = f"{json_name} frame {i} ({listed([file_path], width=ID_SHOWN)})"
        path = find_image(root, file_path)
        if path is None:
            candidates = image_candidates(root, file_path)
            try:
                candidates[0].is_file()
            except OSError as exc:  # e.g. a name over the file system's length limit
                raise _invalid(f"{where}: 'file_path' is not a usable path ({exc.strerror})", staging) from None
            raise _invalid(f"{where}: {image_not_found(root, file_path)}", staging)
        try:
            with warnings.catch_warnings():
                warnings.simplefilter("ignore", Image.DecompressionBombWarning)
                with Image.open(path) as image:
                    size = image.size
        except MemoryError:
            raise
        except Exception as exc:  # as above: any kind Pillow raises means it cannot read the file
            if path.stat().st_size == 0:  # (a failed copy, an empty part): nothing to call damaged
                raise _invalid(f"{where}: cannot read image {path.name}: the file is empty (0 bytes)",
                               staging) from None
            if brand := heif_brand(path):  # a photo, neither damaged nor anything but an image
                raise _invalid(f"{where}: cannot read image {path.name}: it is a HEIF image (brand {brand!r}: an "
                               "iPhone's HEIC photo?), a format not read here: convert it to JPEG or PNG",
                               staging) from None
            raise _invalid(f"{where}: cannot read image {path.name} (not an image or damaged): {exc}", staging) from None
        if first is None:
            first = (size, file_path)
        elif size != first[0]:
            (w, h), ((fw, fh), first_path) = size, first
            raise _invalid(f"{where}: image size {w}x{h} differs from frame 0 ({listed([first_path], width=ID_SHOWN)}) "
                           f"size {fw}x{fh}; all images of a split must share one "
                           f"size{quarter_turn_hint(path, w, h, fw, fh)}", staging)
    return first[0]


def staging_folder(work_dir: Path) -> AbstractContextManager[Path]:
    """A new folder for one upload under ``work_dir/uploads``, removed on leaving, held while it is used
    (:func:`voxe_service.scratch.locked_folder`): :func:`sweep_staging` leaves it alone."""
    return locked_folder(Path(work_dir) / _UPLOADS, _STAGING_PREFIX)


def sweep_staging(work_dir: Path) -> int:
    """Remove the staging folders under ``work_dir/uploads`` no live process holds: those of an API process killed
    mid-upload, kept for ever otherwise; the count removed. Safe beside the API processes sharing ``work_dir``.

    Makes ``work_dir/uploads`` first and a folder in it, as each upload does, so a ``VOXE_WORK_DIR`` that cannot
    hold them (a file, a read-only folder, or one whose ``uploads`` is) stops the API at its start, naming the
    variable (:class:`SettingsError`): every upload had been a 500.
    """
    uploads = Path(work_dir) / _UPLOADS
    try:
        uploads.mkdir(parents=True, exist_ok=True)
        probe = uploads / f".probe-{uuid.uuid4().hex}"
        probe.mkdir()
        probe.rmdir()
    except OSError as exc:
        raise SettingsError(f"bad service settings: VOXE_WORK_DIR={str(work_dir)!r}: cannot make the upload "
                            f"staging folder {str(uploads)!r}: {exc.strerror}") from None
    return sweep_unlocked(uploads, _STAGING_PREFIX + "*")


def stage_upload(
    staging: Path,
    archive: BinaryIO | None,
    files: list[tuple[str, BinaryIO]],
    max_bytes: int,
    max_files: int,
    validation_downsample: int,
    max_ratio: float,
    max_image_pixels: int,
    mesh_shading: str | None = None,
    mesh_up_axis: str | None = None,
    archive_name: str | None = None,
) -> StagedUpload:
    """Unpack, check and pack an upload in ``staging`` (a :func:`staging_folder`, holding the packed archive).

    ``mesh_shading`` (a mesh upload's ``voxe_core.mesh_input.shade_mesh`` mode; default "auto") and
    ``mesh_up_axis`` (its file's up axis, as ``load_mesh`` takes it; default "y") are refused for a
    dataset of images. ``archive_name``: the zip's file name as sent, which its refusals name."""
    if (archive is None) == (not files):
        raise UploadError("send either one zip 'archive' or the dataset's 'files' (with the transforms json)")
    budget = _Budget(max_bytes, max_files, max_ratio)
    unpacked = staging / "data"
    unpacked.mkdir()
    if archive is not None:
        extract_zip(archive, unpacked, budget, archive_name)
    else:
        save_files(files, unpacked, budget)
    check_image_pixels(unpacked, max_image_pixels)
    root = dataset_root(unpacked)
    packed = staging / "packed.zip"
    mesh = pack_mesh_upload(root, staging / "mesh_upload", mesh_shading or "auto", mesh_up_axis or "y")
    if mesh is not None:  # rendered by the ingest into MESH_VIEWS views of MESH_VIEW_SIZE px (train and test)
        package(mesh, packed)
        size = datasets.MESH_VIEW_SIZE
        return StagedUpload(MESH_FORMAT, datasets.MESH_VIEWS, size, size, ["train", "test"], packed, UPLOAD_ARCHIVE)
    for option, value in (("mesh_shading", mesh_shading), ("mesh_up_axis", mesh_up_axis)):
        if value is not None:
            raise UploadError(f"{option} applies to mesh uploads only (.obj or .ply); this upload is a dataset of "
                              "images")
    if (root / datasets.UNPACKED_MARK).is_dir():  # the worker could not write its mark: every job had failed
        raise UploadError(f"the dataset folder holds a folder {datasets.UNPACKED_MARK!r}, the name of the mark a "
                          "worker writes in a dataset it unpacked: rename or remove it")
    fmt, count, width, height, splits = check_dataset(root, unpacked, validation_downsample)
    package(root, packed)
    return StagedUpload(fmt, count, width, height, splits, packed, DATASET_ARCHIVE)
