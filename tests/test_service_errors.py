"""Bad requests to a real `bcf serve`: each gets its own 4xx with a JSON detail that names the problem, and
leaves nothing behind (no stored inputs, artifacts or staging files, no job). Then one valid submission, on a
server of its own so the bad-request tests can count on an empty store wherever pytest runs them."""

from __future__ import annotations

import functools
import io
import json
import os
import re
import zipfile
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, Callable, Iterator

import httpx
import pytest

from crafted_images import png_claiming
from service_harness import BcfEnvironment, Server, material_zip, tiny_material

TOKEN = "secret"
# Small limits so each can be crossed with a small request.
LIMITS = {"api_tokens": TOKEN, "max_upload_mb": 1, "max_unzipped_mb": 4, "max_zip_entries": 8, "job_memory_mb": 1024}
FOLDER = "Chainmail004_1K-PNG"  # material_zip's folder: the job's name
PUBLIC_JOB_FIELDS = {"id", "state", "name", "options", "inputs", "notes", "progress", "error", "created_at",
                     "updated_at", "started_at", "finished_at", "result", "purged_at"}
Files = dict[str, tuple[str, bytes, str]]


@dataclass(frozen=True)
class Service:
    server: Server
    data_dir: Path


def _start(root: Path) -> Iterator[Service]:
    environment = BcfEnvironment(root, **LIMITS)
    server = environment.serve(workers=0)  # no worker: jobs stay queued
    try:
        yield Service(server, environment.data_dir)
    finally:
        server.stop()


@pytest.fixture(scope="module")
def service(tmp_path_factory: pytest.TempPathFactory) -> Iterator[Service]:
    """The server for bad requests only: its store must stay empty."""
    yield from _start(tmp_path_factory.mktemp("errors"))


@pytest.fixture(scope="module")
def accepting(tmp_path_factory: pytest.TempPathFactory) -> Iterator[Service]:
    """A second server for the valid submission, so it cannot make the bad-request checks see a job."""
    yield from _start(tmp_path_factory.mktemp("accepting"))


@functools.cache
def _material(size: int = 64) -> Files:
    """tiny_material reads and encodes PNGs; build each size once per module."""
    return tiny_material(0, size)


def material(size: int = 64) -> Files:
    return dict(_material(size))


def leftovers(data_dir: Path) -> list[str]:
    """Everything under the folders a request may write to (they need not exist)."""
    return sorted(str(p.relative_to(data_dir)) for sub in ("inputs", "artifacts", "uploads")
                  for p in (data_dir / sub).rglob("*"))


def assert_nothing_written(service: Service) -> None:
    assert leftovers(service.data_dir) == []
    listing = service.server.client.get("/v1/jobs")
    assert listing.status_code == 200, listing.text
    assert listing.json()["total"] == 0 and listing.json()["jobs"] == []


def assert_error(response: httpx.Response, status: int, *words: str) -> str:
    """`status` with a JSON {"detail": "..."} that contains each of `words` (case-insensitive)."""
    assert response.status_code == status, response.text
    assert response.headers["content-type"].startswith("application/json"), response.headers
    body = response.json()
    assert set(body) == {"detail"} and isinstance(body["detail"], str), body
    missing = [w for w in words if w.lower() not in body["detail"].lower()]
    assert not missing, f"{missing} not in {body['detail']!r}"
    return body["detail"]


def zip_of(entries: dict[str, bytes], compression: int = zipfile.ZIP_DEFLATED) -> bytes:
    out = io.BytesIO()
    with zipfile.ZipFile(out, "w", compression) as archive:
        for name, data in entries.items():
            archive.writestr(zipfile.ZipInfo(name), data, compress_type=compression)
    return out.getvalue()


def material_entries() -> dict[str, bytes]:
    """The valid material as zip entries under its folder."""
    return {f"{FOLDER}/{name}": data for name, data, _ in material().values()}


def zip_with_symlink() -> bytes:
    out = io.BytesIO(zip_of(material_entries()))
    with zipfile.ZipFile(out, "a") as archive:
        link = zipfile.ZipInfo(f"{FOLDER}/link.png")
        link.external_attr = 0o120777 << 16  # S_IFLNK | rwxrwxrwx, as zip -y stores a link
        archive.writestr(link, "../../../etc/passwd")
    return out.getvalue()


def zip_with_bad_crc() -> bytes:
    """The valid material zip (stored, not deflated) with one byte of the first entry's data flipped."""
    data = bytearray(zip_of(material_entries(), zipfile.ZIP_STORED))
    with zipfile.ZipFile(io.BytesIO(bytes(data))) as archive:
        first = archive.infolist()[0]
    data[first.header_offset + 30 + len(first.filename.encode()) + 100] ^= 0xFF  # 30: local header size
    return bytes(data)


def as_material(data: bytes, name: str = "material.zip") -> Files:
    return {"material": (name, data, "application/zip")}


def post(service: Service, **request: Any) -> httpx.Response:
    """POST /v1/jobs on a connection of its own, so a server error that drops it cannot break later tests."""
    with httpx.Client(base_url=service.server.url, headers={"Authorization": f"Bearer {TOKEN}"},
                      timeout=60) as client:
        return client.post("/v1/jobs", **request)


# ------------------------------------------------------------------------------------------ authorisation


@pytest.mark.parametrize("headers", [{}, {"Authorization": "Bearer wrong"}, {"Authorization": "secret"}],
                         ids=["no-header", "wrong-token", "no-bearer-scheme"])
@pytest.mark.parametrize("method,path", [("POST", "/v1/jobs"), ("GET", "/v1/jobs"), ("GET", "/metrics")])
def test_requests_without_the_token_are_refused(service: Service, headers: dict[str, str], method: str,
                                                path: str) -> None:
    files = material() if method == "POST" else None  # a valid material: only the token is wrong
    response = httpx.request(method, service.server.url + path, headers=headers, files=files, timeout=30)
    assert_error(response, 401, "bearer token")
    assert response.headers["www-authenticate"] == "Bearer"
    assert_nothing_written(service)


def test_healthz_needs_no_token(service: Service) -> None:
    response = httpx.get(service.server.url + "/healthz", timeout=30)
    assert response.status_code == 200, response.text
    assert response.json()["status"] == "ok" and response.json()["mode"] == "embedded"


# ------------------------------------------------------------------------------------------- bad uploads


@dataclass(frozen=True)
class BadRequest:
    """A POST /v1/jobs body and what the API must answer."""

    status: int
    words: tuple[str, ...]
    files: Callable[[], Files]
    data: dict[str, Any] = field(default_factory=dict)  # form fields; a list repeats the field


def options(value: Any) -> dict[str, Any]:
    """The options form field: `value` as JSON, or as it is when a str (to send broken JSON)."""
    return {"options": value if isinstance(value, str) else json.dumps(value)}


def _replace(role: str, value: tuple[str, bytes, str]) -> Callable[[], Files]:
    return lambda: material() | {role: value}


def _without(role: str) -> Callable[[], Files]:
    return lambda: {r: f for r, f in material().items() if r != role}


def _mismatched() -> Files:
    """albedo 64x64, every other role 128x128."""
    return material(128) | {"albedo": material()["albedo"]}


BAD_UPLOADS: dict[str, BadRequest] = {
    "over-upload-limit": BadRequest(413, ("larger than the limit", "1 MiB"),
                                    _replace("albedo", ("albedo.png", os.urandom(2 << 20), "image/png"))),
    "pixel-bomb": BadRequest(422, ("albedo", "16384x16384 is 268,435,456 pixels", "limit of 67,108,864"),
                             _replace("albedo", ("albedo.png", png_claiming(16384, 16384), "image/png"))),
    "text-as-png": BadRequest(415, ("albedo", "albedo.png", "not a PNG"),
                              _replace("albedo", ("albedo.png", b"just some text, not pixels\n" * 8, "image/png"))),
    "zip-not-a-zip": BadRequest(415, ("material", "not a zip"),
                                lambda: as_material(b"PK but not really a zip archive" * 4)),
    "mismatched-sizes": BadRequest(422, ("differ in size", "64x64", "128x128", "Chainmail004_1K_Color.png"),
                                   _mismatched),
    "missing-normal": BadRequest(422, ("incomplete material", "missing normal", "the form fields albedo, normal"),
                                 _without("normal")),
    "arm-and-separate-maps": BadRequest(422, ("arm (Chainmail004_1K_Roughness.png)", "the form field arm cannot be "
                                              "combined with the form fields roughness, metalness"),
                                        lambda: material() | {"arm": material()["roughness"]}),
    "zip-traversal": BadRequest(400, ("../evil.png", "outside the archive"),
                                lambda: as_material(zip_of(material_entries() | {"../evil.png": b"x"}))),
    "zip-absolute": BadRequest(400, ("/abs.png", "outside the archive"),
                               lambda: as_material(zip_of(material_entries() | {"/abs.png": b"x"}))),
    "zip-bomb": BadRequest(413, ("uncompressed", "limit of 4 MiB"),
                           lambda: as_material(zip_of({f"{FOLDER}/albedo.png": bytes(8 << 20)}))),
    "zip-too-many-entries": BadRequest(400, ("9 entries", "limit of 8"), lambda: as_material(zip_of(
        material_entries() | {f"{FOLDER}/extra{i}.txt": b"x" for i in range(9 - len(material()))}))),
    "zip-symlink": BadRequest(400, ("link.png", "symbolic link"), lambda: as_material(zip_with_symlink())),
    "zip-and-role-files": BadRequest(400, ("either", "not both"), lambda: as_material(
        material_zip(material())) | {"albedo": material()["albedo"]}),
    "unknown-field": BadRequest(400, ("unknown form field", "albdo"),
                                lambda: {"albdo" if r == "albedo" else r: f for r, f in material().items()}),
    "options-not-json": BadRequest(422, ("options", "json"), material, options("{preset: fast")),
    "options-unknown-key": BadRequest(422, ("options", "speed", "not permitted"), material, options({"speed": 11})),
    "options-bad-preset": BadRequest(422, ("preset", "fast", "paper"), material, options({"preset": "slow"})),
    "options-device": BadRequest(422, ('options {"device": ...}', "chosen by the worker"), material,
                                 options({"device": "cuda"})),
    "options-bad-baseline": BadRequest(422, ("baseline", "nope"), material, options({"baselines": ["nope"]})),
    "options-endless": BadRequest(422, ("phase2_iterations", "less than or equal"), material,
                                  options({"phase2_iterations": 10**12})),
    "options-huge-batch": BadRequest(422, ("batch_size", "less than or equal"), material,
                                     options({"batch_size": 10**9})),
    "options-seed-overflow": BadRequest(422, ("seed", "less than or equal"), material, options({"seed": 2**64})),
    "options-wild-rate": BadRequest(422, ("lr_features_phase2", "less than or equal"), material,
                                    options({"lr_features_phase2": 1e30})),
    "over-memory-budget": BadRequest(422, ("64x64", "training batches of 1048576", "more than the budget of 1.0 GiB",
                                           "BCF_JOB_MEMORY_MB"), material,
                                     options({"preset": "fast", "phase2_iterations": 1, "batch_size": 2**20})),
    "options-twice": BadRequest(400, ("once",), material, {"options": ['{"preset": "fast"}', "{}"]}),
}


@pytest.mark.parametrize("case", BAD_UPLOADS.values(), ids=BAD_UPLOADS.keys())
def test_bad_upload_is_refused_and_leaves_nothing(service: Service, case: BadRequest) -> None:
    detail = assert_error(post(service, files=case.files(), data=case.data), case.status, *case.words)
    assert str(service.data_dir) not in detail, "the message shows a server path"
    assert not re.search(r"--(albedo|normal|arm|ao|roughness|metalness|force)\b", detail), "a CLI flag, not a field"
    assert_nothing_written(service)


def test_chunked_upload_over_the_limit_is_413(service: Service) -> None:
    """Without Content-Length the limit is enforced while the body streams in (RequestGate's counting receive).
    Fails today: FastAPI turns the limit's exception into 400 "There was an error parsing the body"."""
    files = material() | {"albedo": ("albedo.png", os.urandom(2 << 20), "image/png")}
    request = service.server.client.build_request("POST", "/v1/jobs", files=files)
    body = request.read()
    chunks = (body[i:i + 65536] for i in range(0, len(body), 65536))  # a generator: sent chunked
    response = post(service, content=chunks, headers={"content-type": request.headers["content-type"]})
    assert response.request.headers.get("transfer-encoding") == "chunked"
    assert_error(response, 413, "larger than the limit", "1 MiB")
    assert_nothing_written(service)


def test_zip_with_a_corrupt_entry_is_415(service: Service) -> None:
    """A zip whose directory reads but whose entry data is damaged (CRC mismatch) is the client's problem.
    Fails today: zipfile.BadZipFile escapes _unpack_zip while extracting and the API answers 500."""
    response = post(service, files=as_material(zip_with_bad_crc()))
    assert response.status_code != 500, "corrupt zip entry crashed the request handler (500)"
    assert_error(response, 415, "Chainmail004_1K_Color.png")
    assert_nothing_written(service)


# --------------------------------------------------------------------------------------------- no such job


@pytest.mark.parametrize("method,suffix", [("GET", ""), ("DELETE", ""), ("GET", "/report"),
                                           ("GET", "/artifacts"), ("GET", "/artifacts/x")])
def test_unknown_job_is_404(service: Service, method: str, suffix: str) -> None:
    response = service.server.client.request(method, f"/v1/jobs/0123456789abcdef{suffix}")
    assert_error(response, 404, "no job", "0123456789abcdef")
    assert_nothing_written(service)


@pytest.mark.parametrize("query", ["offset=9223372036854775808", "offset=-1", "limit=0", "limit=1001"])
def test_job_list_paging_out_of_range_is_422(service: Service, query: str) -> None:
    """Beyond SQLite's 64-bit integers the store used to fail with a 500 (schemathesis, issue 16 case 9)."""
    assert_error(service.server.client.get(f"/v1/jobs?{query}"), 422, query.split("=")[0])


# ------------------------------------------------------------------------------------- a valid submission


def test_valid_zip_is_queued_deduplicated_cancelled_and_counted(accepting: Service) -> None:
    client, data_dir = accepting.server.client, accepting.data_dir
    upload = as_material(material_zip(material()), "my upload.zip")

    response = client.post("/v1/jobs", files=upload)
    assert response.status_code == 202, response.text
    job = response.json()
    assert job["state"] == "queued" and job["name"] == FOLDER
    assert response.headers["location"] == f"/v1/jobs/{job['id']}"
    assert isinstance(job["notes"], list)
    assert set(job) == PUBLIC_JOB_FIELDS, "the answer shows the public job, not the stored record"
    # Inputs are stored as <role>/<file name>, one folder per role; the zip's own name and folder are not used.
    stored = data_dir / "inputs" / job["id"]
    names = {role: name for role, (name, _, _) in material().items()}
    assert sorted(str(p.relative_to(stored)) for p in stored.glob("*/*")) == sorted(f"{r}/{n}"
                                                                                   for r, n in names.items())
    assert all((stored / role / name).read_bytes() == material()[role][1] for role, name in names.items())
    assert [{"role": f["role"], "name": f["name"]} for f in job["inputs"]] == [{"role": r, "name": n}
                                                                           for r, n in names.items()]
    assert all(set(f) == {"role", "name", "sha256", "bytes"} for f in job["inputs"])
    assert not [p for p in data_dir.rglob("*") if p.name in {FOLDER, "my upload.zip", "my_upload"}]
    assert not [p for p in (data_dir / "uploads").rglob("*")], "staging left behind"
    record = accepting.server.stored(job["id"])
    assert record.attempts == 0 and record.worker is None and len(record.input_key) == 64

    again = client.post("/v1/jobs", files=upload)
    assert again.status_code == 200, again.text
    assert again.json()["id"] == job["id"]
    assert [p.name for p in (data_dir / "inputs").iterdir()] == [job["id"]]

    queued = client.get("/v1/jobs", params={"state": "queued"})
    assert queued.status_code == 200, queued.text
    assert queued.json()["total"] == 1 and [j["id"] for j in queued.json()["jobs"]] == [job["id"]]
    assert set(queued.json()["jobs"][0]) == PUBLIC_JOB_FIELDS

    cancelled = client.delete(f"/v1/jobs/{job['id']}")
    assert cancelled.status_code == 200, cancelled.text
    assert cancelled.json()["state"] == "cancelled" and cancelled.json()["finished_at"] is not None
    assert set(cancelled.json()) == PUBLIC_JOB_FIELDS
    assert client.get(f"/v1/jobs/{job['id']}").json()["state"] == "cancelled"

    metrics = client.get("/metrics")
    assert metrics.status_code == 200 and metrics.headers["content-type"].startswith("text/plain")
    assert re.search(r'^bcf_jobs\{state="cancelled"\} 1$', metrics.text, re.M), metrics.text
    assert re.search(r'^bcf_jobs\{state="queued"\} 0$', metrics.text, re.M), metrics.text
    assert re.search(r"^bcf_queue_depth \d+$", metrics.text, re.M), metrics.text

    assert_error(client.get(f"/v1/jobs/{job['id']}/report"), 409, job["id"], "cancelled")

    # A cancelled job no longer holds its inputs' key: the same zip makes a new job.
    fresh = client.post("/v1/jobs", files=upload)
    assert fresh.status_code == 202, fresh.text
    assert fresh.json()["id"] != job["id"] and fresh.json()["state"] == "queued"


def test_role_files_are_stored_under_their_safe_names(accepting: Service) -> None:
    """A client's file name becomes a file name inside its role's folder only after it is made safe: no path
    parts, no hidden names, only [A-Za-z0-9._-], and the extension of the format its bytes show."""
    files = material() | {"albedo": ("../../My Color (final).PNG", material()["albedo"][1], "image/png"),
                          "normal": (".hidden", material()["normal"][1], "image/png"),
                          "roughness": ("rough.jpg", material()["roughness"][1], "image/png")}
    response = accepting.server.client.post("/v1/jobs", files=files, data=options({"seed": 7}))
    assert response.status_code == 202, response.text
    job = response.json()
    stored = accepting.data_dir / "inputs" / job["id"]
    assert sorted(str(p.relative_to(stored)) for p in stored.glob("*/*")) == [
        "albedo/My_Color_final.PNG", "metalness/Chainmail004_1K_Metalness.png", "normal/hidden.png",
        "roughness/rough.png"]
    assert job["name"] == "My_Color_final"
    shown = {f["role"]: f["name"] for f in job["inputs"]}
    assert shown["normal"] == ".hidden" and shown["roughness"] == "rough.jpg"  # as sent: for display only
    assert accepting.server.stored(job["id"]).inputs[0].stored_as == "albedo/My_Color_final.PNG"


def test_openapi_and_docs_are_served(accepting: Service) -> None:
    schema = accepting.server.client.get("/openapi.json")
    assert schema.status_code == 200, schema.text
    assert {"/v1/jobs", "/v1/jobs/{job_id}", "/metrics"} <= set(schema.json()["paths"])
    # The documented job is the public one (docs/SERVICE.md describes the same fields).
    assert set(schema.json()["components"]["schemas"]["JobView"]["properties"]) == PUBLIC_JOB_FIELDS
    assert "Job" not in schema.json()["components"]["schemas"]
    docs = accepting.server.client.get("/docs")
    assert docs.status_code == 200 and "swagger" in docs.text.lower()


# The error codes each operation can answer, as the tests above provoke them (issue 16, case 9).
DOCUMENTED_ERRORS = {
    ("post", "/v1/jobs"): {400, 401, 413, 415, 422, 503, 507},
    ("get", "/v1/jobs"): {401, 422, 503},
    ("get", "/v1/jobs/{job_id}"): {401, 404, 422, 503},
    ("delete", "/v1/jobs/{job_id}"): {401, 404, 409, 422, 503},
    ("get", "/v1/jobs/{job_id}/report"): {401, 404, 409, 410, 422, 503},
    ("get", "/v1/jobs/{job_id}/artifacts"): {401, 404, 409, 410, 422, 503},
    ("get", "/v1/jobs/{job_id}/artifacts/{name}"): {401, 404, 409, 410, 422, 503},
    ("get", "/metrics"): {401, 503},
    ("get", "/healthz"): {503},
}


def test_the_openapi_document_states_every_error_and_its_body(service: Service) -> None:
    """Every error an operation sends is in the document, with the body the service really sends
    ({"detail": "..."}, a string), and FastAPI's own 422 body (a list) is nowhere."""
    document = service.server.client.get("/openapi.json").json()
    assert document["components"]["schemas"]["ErrorBody"]["properties"] == {
        "detail": {"type": "string", "title": "Detail"}}
    assert "HTTPValidationError" not in document["components"]["schemas"]
    for (method, path), codes in DOCUMENTED_ERRORS.items():
        responses = document["paths"][path][method]["responses"]
        errors = {int(code) for code in responses if int(code) >= 400}
        assert errors == codes, (method, path, sorted(errors))
        for code in errors:
            schema = responses[str(code)]["content"]["application/json"]["schema"]
            assert schema == {"$ref": "#/components/schemas/ErrorBody"}, (method, path, code, schema)
    ready = document["paths"]["/readyz"]["get"]["responses"]["503"]["content"]["application/json"]["schema"]
    assert ready == {"$ref": "#/components/schemas/Readiness"}
