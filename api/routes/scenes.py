"""/v1/scenes: upload (cheap checks at once, the full decode by a worker's ingest), list, get, delete."""

from __future__ import annotations

from typing import Annotated, Literal

from fastapi import APIRouter, Depends, File, Form, HTTPException, Request, Response, UploadFile, params, status
from pydantic import AfterValidator
from starlette.exceptions import HTTPException as StarletteHTTPException

from api.auth import mark_replayed, replayed_answer
from api.deps import CurrentKey, IdempotencyKey, QueueDep, SessionDep, SettingsDep, StorageDep
from api.http_semantics import (FORM_MEDIA_TYPE, StrictRoute, media_type, media_type_shown, refuse_encoded,
                                sends_body, takes_several)
from api.paging import PageQuery, page_query
from api.schemas import SCENE_NAME_PATTERN, Page, ReconstructionOut, SceneOut, scene_name
from api.services import scenes
from api.uploads import too_many_files
from voxe_service.settings import get_settings
from voxe_service.texts import listed


class UploadFilesRoute(StrictRoute):
    """A form route whose multipart body is parsed allowing ``VOXE_MAX_UPLOAD_FILES`` files, before FastAPI parses it
    (then reusing this parse): Starlette's default of 1000 had answered an upload of 1001 ``files`` 400 "Too many
    files". More than the setting is the upload's own 413. A one-valued field sent twice (``-F name=a -F name=b``) is
    a 422 naming it: the last had silently won.

    A part of the wrong kind is a 4xx naming the field: a text field where a file is expected (``curl -F
    archive=<scene.zip``) had been a 422 "Expected UploadFile, received: <class 'str'>" (over Starlette's 1 MB per
    text field, a 400 "Part exceeded maximum size of 1024KB."), and a file where text is expected a 422 dumping the
    server's upload object. A part no field takes is a 422 naming it: a misspelt ``mesh_shadng=baked`` had been
    ignored, the scene made without it. A body sent as another media type than multipart/form-data (a raw zip, JSON;
    a urlencoded form, curl --data-binary's default, which cannot carry a file), or a body with no media type, is a
    415 naming it: it had been read as an empty form, a 422 "send either one zip 'archive' or the dataset's 'files'"
    (a urlencoded one as field names: a 422 naming the whole body). A file part named only by ``filename*=UTF-8''...``
    (RFC 5987's form, which RFC 7578 says senders should not use; some clients do) is a text field to Starlette: its
    422 says so."""

    def get_route_handler(self):
        handler = super().get_route_handler()
        if not (self.body_field and isinstance(self.body_field.field_info, params.Form)):
            return handler
        file_fields = [f.alias for f in self.dependant.body_params if isinstance(f.field_info, params.File)]
        text_fields = [f.alias for f in self.dependant.body_params if f.alias not in file_fields]
        several = [f.alias for f in self.dependant.body_params if takes_several(f.field_info.annotation)]

        def as_file(field: str) -> str:
            return f"a part with a filename: curl -F '{field}=@<path>'"

        async def parse_then_handle(request: Request) -> Response:
            self.refuse_odd_query(request)  # before the form is read (the handler checks it again)
            refuse_encoded(request)
            if (sent_as := media_type(request)) != FORM_MEDIA_TYPE and (sent_as or sends_body(request)):
                raise HTTPException(status.HTTP_415_UNSUPPORTED_MEDIA_TYPE,
                                    f"the body must be sent as a form ({FORM_MEDIA_TYPE}, as curl -F sends it), not "
                                    f"as {media_type_shown(request)}")
            max_files = get_settings().max_upload_files
            try:
                form = await request.form(max_files=max_files)
            except StarletteHTTPException as exc:  # Starlette's 400 for a form it refuses
                if exc.status_code == 400 and str(exc.detail).startswith("Too many files"):
                    raise HTTPException(status.HTTP_413_CONTENT_TOO_LARGE, too_many_files(max_files)) from None
                if exc.status_code == 400 and (limit := _header_limit(exc)):  # a bare "Invalid multipart data."
                    raise HTTPException(status.HTTP_400_BAD_REQUEST, limit) from None
                # A text part's: Starlette's message names no field, so this one says what each field takes.
                if exc.status_code == 400 and "exceeded maximum size" in str(exc.detail) and file_fields:
                    raise HTTPException(status.HTTP_413_CONTENT_TOO_LARGE,
                                        f"a text field of the form is too long ({exc.detail}): "
                                        f"{', '.join(map(repr, text_fields))} take short text; "
                                        f"{' or '.join(map(repr, file_fields))} take a file "
                                        f"({as_file(file_fields[0])})") from None
                raise
            for field in self.dependant.body_params:
                wants_file = isinstance(field.field_info, params.File)
                for part in form.getlist(field.alias):
                    if part == "" and not takes_several(field.field_info.annotation):  # FastAPI's "not sent"
                        continue
                    if wants_file and isinstance(part, str):  # (Starlette keeps no part's headers: no more said)
                        raise HTTPException(status.HTTP_422_UNPROCESSABLE_CONTENT, f"{field.alias!r} must be a file "
                                            f"({as_file(field.alias)}), not a text field: a part whose "
                                            "Content-Disposition has no filename= parameter, as one naming its file "
                                            "only by RFC 5987's filename*= has not, is read as text (RFC 7578: "
                                            "send filename=\"...\")")
                    if not wants_file and not isinstance(part, str):
                        raise HTTPException(status.HTTP_422_UNPROCESSABLE_CONTENT,
                                            f"{field.alias!r} must be a text field, not a file ({part.filename!r})")
            if unknown := sorted(set(form.keys()) - {*file_fields, *text_fields}):
                raise HTTPException(status.HTTP_422_UNPROCESSABLE_CONTENT,
                                    f"unknown form field(s) {listed(unknown)}: the upload takes "
                                    f"{', '.join(map(repr, [*file_fields, *text_fields]))}")
            if twice := [alias for alias in [*file_fields, *text_fields]
                         if alias not in several and len(form.getlist(alias)) > 1]:  # the last had silently won
                raise HTTPException(status.HTTP_422_UNPROCESSABLE_CONTENT,
                                    f"form field(s) {listed(twice)} sent more than once: send each once "
                                    f"(only {listed(several)} may be sent several times)")
            return await handler(request)

        return parse_then_handle


def _header_limit(refused: StarletteHTTPException) -> str | None:
    """What a form refused for a part's headers over the multipart parser's limits hit (Starlette's 400 names none:
    "Invalid multipart data."; its parse error is the cause of the exception it answered), or None for another 400.
    A file name nested 3,000 folders deep is such a header."""
    cause = getattr(refused.__context__, "__cause__", None)
    if cause is None or not str(cause).startswith("Maximum header"):
        return None
    from python_multipart.multipart import DEFAULT_MAX_HEADER_COUNT, DEFAULT_MAX_HEADER_SIZE  # (versions with them)

    if "count" in str(cause):
        return f"a part of the form has more than {DEFAULT_MAX_HEADER_COUNT} headers, the most the form parser reads"
    return (f"a part of the form has a header line longer than {DEFAULT_MAX_HEADER_SIZE:,} bytes, the most the form "
            "parser reads: a file name that long (a path of many folders?) cannot be sent; shorten it")


router = APIRouter(prefix="/v1/scenes", tags=["scenes"], route_class=UploadFilesRoute)

_ERRORS = {404: {"description": "no such scene (or another key's)"}}


def scene_out(scene) -> SceneOut:
    return SceneOut.model_validate(scene, from_attributes=True)


@router.post(
    "",
    status_code=status.HTTP_201_CREATED,
    response_model=SceneOut,
    responses={200: replayed_answer(SceneOut, "scene"),
               401: {"description": "missing or invalid API key"},
               409: {"description": "a retry whose Idempotency-Key created a scene that has since been deleted, or "
                                    "one sent while that first request has not answered yet (Retry-After); or the "
                                    "scene was deleted before its upload answered"},
               413: {"description": "upload over a limit: its size, its count of files, a zip's compression ratio or "
                                    "an image's pixels (the message names the setting)"},
               422: {"description": "not a valid dataset (the message names the file and frame), a form field "
                                    "the upload does not take, of the wrong kind, or one-valued and sent twice "
                                    "(named), or an Idempotency-Key reused with a different upload"},
               429: {"description": "the key's upload quota is used up (no Retry-After: deleting scenes frees it, "
                                    "waiting does not)"},
               503: {"description": "the ingest could not be queued (broker unreachable)"}},
    summary="Upload a posed image set or a mesh (optionally with an Idempotency-Key header)",
)
def create_scene(
    response: Response,
    session: SessionDep,
    settings: SettingsDep,
    storage: StorageDep,
    queue: QueueDep,
    key: CurrentKey,
    idempotency_key: IdempotencyKey,
    archive: UploadFile | None = File(
        None, description="a zip of a NeRF-synthetic folder (transforms_train.json, ...), an instant-ngp / "
                          "nerfstudio folder (transforms.json, camera_model with k1..k4, p1, p2), a COLMAP model "
                          "(sparse/0/ or sparse/ cameras.bin|txt and images.bin|txt beside images/), or one mesh "
                          "(.obj with its texture and .mtl, or .ply); the folder may be the archive root or its only "
                          "top-level folder"),
    files: list[UploadFile] | None = File(
        None, description="alternatively the dataset's files, each named by its path in the dataset folder "
                          "(e.g. transforms.json, images/0001.png)"),
    name: Annotated[str | None, Form(
        max_length=255, json_schema_extra={"pattern": SCENE_NAME_PATTERN},
        description="display name (default: the zip's file name, or the mesh's, or the one folder the files are in; "
                    "else scene-<id>); one line of text: no control characters, not blank"),
        AfterValidator(scene_name)] = None,  # (after the Form: with the Form as the default, FastAPI drops it)
    mesh_shading: Literal["auto", "baked", "none"] | None = Form(
        None, description="a mesh upload's colour: baked bakes a fixed key light and ambient occlusion into it, none "
                          "keeps the bare albedo, auto (the default) bakes it only for a mesh without texture or "
                          "vertex colours (else it would be one flat grey); refused for image datasets"),
    mesh_up_axis: Literal["x", "y", "z"] | None = Form(
        None, description="a mesh upload's up axis, turned onto +z: y (the default) for OBJ and glTF exports, z for "
                          "CAD and most scanners; refused for image datasets"),
) -> SceneOut:
    """201 with the new scene, ``processing`` until a worker has decoded it (then ``ready``, or ``failed`` with
    the reason); 200 with the original one for a retry carrying the same Idempotency-Key."""
    upload = scenes.Upload(archive=archive.file if archive is not None else None,
                           archive_name=archive.filename if archive is not None else None,
                           files=[(f.filename or "", f.file) for f in files or []], name=name,
                           mesh_shading=mesh_shading, mesh_up_axis=mesh_up_axis)
    scene, replayed = scenes.create_scene(session=session, settings=settings, storage=storage, queue=queue, key=key,
                                          upload=upload, idempotency_key=idempotency_key)
    if replayed:
        mark_replayed(response)
    return scene_out(scene)


@router.get("", response_model=Page[SceneOut], summary="List scenes, newest first",
            responses={422: {"description": "a limit or offset out of range, or a cursor that is not this "
                                              "listing's or is sent with offset (named)"}})
def list_scenes(
    session: SessionDep,
    key: CurrentKey,
    page: Annotated[PageQuery, Depends(page_query("/v1/scenes"))],
) -> Page[SceneOut]:
    found = scenes.list_scenes(session=session, key=key, page=page)
    return Page[SceneOut](items=[scene_out(s) for s in found.rows], total=found.total, limit=page.limit,
                          offset=found.offset, next_cursor=found.next_cursor)


@router.get("/{scene_id}", response_model=SceneOut, responses=_ERRORS,
            summary="A scene, with its state: processing, ready, or failed (and why)")
def get_scene(scene_id: str, session: SessionDep, key: CurrentKey) -> SceneOut:
    return scene_out(scenes.get_scene(session=session, key=key, scene_id=scene_id))


@router.get("/{scene_id}/reconstructions", response_model=list[ReconstructionOut], responses=_ERRORS,
            summary="The scene's cached reconstructions (one per reconstruction-parameter set)")
def list_reconstructions(scene_id: str, session: SessionDep, key: CurrentKey) -> list[ReconstructionOut]:
    rows = scenes.list_reconstructions(session=session, key=key, scene_id=scene_id)
    return [ReconstructionOut.model_validate(r, from_attributes=True) for r in rows]


@router.delete("/{scene_id}", status_code=status.HTTP_204_NO_CONTENT,
               responses={**_ERRORS, 409: {"description": "the scene has queued or running jobs (canceled ones "
                                                           "still stopping too: the message says which)"}})
def delete_scene(scene_id: str, session: SessionDep, storage: StorageDep, key: CurrentKey) -> None:
    scenes.delete_scene(session=session, storage=storage, key=key, scene_id=scene_id)
