"""/datasets over HTTP: archive uploads (every bad input a 4xx in the error shape), frame-by-frame uploads,
list, inspect, delete, and the OpenAPI description."""

from __future__ import annotations

import io
import json
import tarfile
import zipfile

import pytest
from fastapi.testclient import TestClient

from model.io.exr import write_frame
from service.datasets import archives, staged
from service.http.routes import datasets

BUFFERS = ["color", "albedo", "specular_albedo", "diffuse", "specular", "normal", "depth", "roughness", "motion",
           "reference"]


@pytest.fixture
def api(make_app) -> TestClient:
    return TestClient(make_app(datasets.router))


@pytest.fixture
def two_sequences(tmp_path, tiny_sequence):
    """A folder with sequence folders seq_a (2 frames, scene cornell) and seq_b (3 frames, scene kitchen)."""
    root = tmp_path / "upload"
    tiny_sequence(root / "seq_a", 2)
    tiny_sequence(root / "seq_b", 3, scene="kitchen", seed=10)
    return root


def post_archive(api, body: bytes, path: str = "/datasets", content_type: str = "application/zip", **params):
    return api.post(path, content=body, headers={"Content-Type": content_type}, params=params)


def assert_error(response, status: int, code: str, *fragments: str) -> dict:
    assert response.status_code == status, response.text
    error = response.json()["error"]
    assert error["code"] == code, error
    for fragment in fragments:
        assert fragment in error["message"], error["message"]
    return error


def assert_nothing_stored(storage) -> None:
    assert list(storage.datasets.iterdir()) == []
    assert [p.name for p in storage.staging.iterdir() if p.name != "locks"] == []


def zip_bytes(members: dict[str, bytes]) -> bytes:
    buffer = io.BytesIO()
    with zipfile.ZipFile(buffer, "w") as bundle:
        for name, data in members.items():
            bundle.writestr(name, data)
    return buffer.getvalue()


def frame_bytes(tmp_path, frame, name="frame.exr") -> bytes:
    return write_frame(tmp_path / name, frame).read_bytes()


# --- archive uploads ---------------------------------------------------------------------------------------


@pytest.mark.parametrize("kind", ["zip", "tar", "tar.gz"])
def test_upload_stores_every_sequence_and_inspect_describes_it(api, storage, two_sequences, make_archive, kind):
    content_type = {"zip": "application/zip", "tar": "application/x-tar", "tar.gz": "application/gzip"}[kind]
    response = post_archive(api, make_archive(two_sequences, kind), content_type=content_type, name="tiny")
    assert response.status_code == 201, response.text
    assert response.headers["location"] == "/datasets/tiny"
    detail = response.json()
    assert detail["id"] == "tiny" and detail["frames"] == 5 and detail["scenes"] == ["cornell", "kitchen"]
    assert detail["sequences"][0] == {
        "name": "seq_a", "split": "train", "scene": "cornell", "frames": 2, "width": 8, "height": 8, "scales": [1],
        "buffers": BUFFERS, "camera_cuts": [0],
    }
    assert detail["splits"]["train"]["sequences"] == 2 and detail["splits"]["test"]["frames"] == 0
    assert api.get("/datasets/tiny").json() == detail
    assert api.get("/datasets").json() == [{"id": "tiny", "sequences": 2, "frames": 5,
                                            "scenes": ["cornell", "kitchen"],
                                            "splits": {"train": 2, "validation": 0, "test": 0}}]
    stored = storage.datasets / "tiny"
    assert sorted(p.name for p in stored.iterdir()) == ["manifest.json", "seq_a", "seq_b"]
    assert [p.name for p in storage.staging.iterdir() if p.name != "locks"] == []  # staging cleaned


def test_wrapping_folder_octet_stream_split_and_generated_id(api, two_sequences, make_archive):
    body = make_archive(two_sequences, "tar.gz", prefix="export/renders/")
    response = post_archive(api, body, content_type="application/octet-stream", split="validation")
    assert response.status_code == 201, response.text
    detail = response.json()
    assert detail["id"].startswith("dataset-") and response.headers["location"] == f"/datasets/{detail['id']}"
    assert {s["split"] for s in detail["sequences"]} == {"validation"}


def test_whole_dataset_folder_keeps_its_splits(api, tmp_path, tiny_sequence, make_archive):
    root = tmp_path / "mydata"
    tiny_sequence(root / "train_0")
    tiny_sequence(root / "held_out", seed=5)
    manifest = {"format": "denoiser-dataset/1", "sequences": {"train_0": {"split": "train", "scene": "cornell"},
                                                              "held_out": {"split": "test", "scene": "cornell"}}}
    (root / "manifest.json").write_text(json.dumps(manifest))
    response = post_archive(api, make_archive(root, "zip", prefix="mydata/"), name="splits", split="validation")
    assert response.status_code == 201, response.text
    assert {s["name"]: s["split"] for s in response.json()["sequences"]} == {"train_0": "train", "held_out": "test"}


def test_existing_name_is_409_before_the_body_counts(api, storage, two_sequences, make_archive):
    body = make_archive(two_sequences)
    assert post_archive(api, body, name="tiny").status_code == 201
    assert_error(post_archive(api, body, name="tiny"), 409, "dataset_exists", "'tiny' already exists",
                 "POST /datasets/tiny/sequences")


@pytest.mark.parametrize("body, fragment", [
    (b"hello, this is plain text and no archive at all", "not a zip, tar or tar.gz"),
    (b"PK\x03\x04" + b"\x00" * 40, "corrupt or truncated"),
    (b"\x1f\x8b\x08\x00" + b"\x00" * 40, "corrupt or truncated"),
])
def test_not_an_archive_is_400(api, storage, body, fragment):
    assert_error(post_archive(api, body), 400, "invalid_archive", fragment)
    assert_nothing_stored(storage)


def test_truncated_archive_is_400(api, storage, two_sequences, make_archive):
    body = make_archive(two_sequences, "tar.gz")
    assert_error(post_archive(api, body[: len(body) // 2]), 400, "invalid_archive", "corrupt or truncated")
    assert_nothing_stored(storage)


def test_empty_body_is_400(api):
    assert_error(post_archive(api, b""), 400, "empty_body", "empty")


def test_wrong_content_type_is_415(api):
    assert_error(post_archive(api, b"x", content_type="text/plain"), 415, "unsupported_media_type",
                 "text/plain", "application/zip")


def test_bad_query_values_are_422_in_the_error_shape(api):
    assert_error(post_archive(api, b"x", split="holdout"), 422, "invalid_request", "split")


def test_invalid_name_is_400(api):
    assert_error(post_archive(api, b"x", name="../up"), 400, "invalid_name", "'../up' is not a valid id")


@pytest.mark.parametrize("streamed", [False, True], ids=["content-length", "chunked"])
def test_too_large_upload_is_413_and_leaves_nothing(make_app, storage, two_sequences, make_archive, streamed):
    api = TestClient(make_app(datasets.router, max_upload_bytes=1000))
    body = make_archive(two_sequences)
    content = (body[i:i + 256] for i in range(0, len(body), 256)) if streamed else body
    response = api.post("/datasets", content=content, headers={"Content-Type": "application/zip"})
    error = assert_error(response, 413, "payload_too_large", "the limit is 1000 bytes")
    assert error["details"] == {"limit_bytes": 1000}
    assert_nothing_stored(storage)


def test_archive_unpacking_past_the_limit_is_413(make_app, storage):
    api = TestClient(make_app(datasets.router, max_unpacked_bytes=40_000))
    buffer = io.BytesIO()
    with zipfile.ZipFile(buffer, "w", zipfile.ZIP_DEFLATED) as bundle:
        bundle.writestr("seq/frame_0000.exr", b"\x00" * 200_000)  # compresses to a few hundred bytes
    assert_error(post_archive(api, buffer.getvalue()), 413, "payload_too_large", "more than 40000 bytes")
    assert_nothing_stored(storage)


def deflated_zip(members: dict[str, bytes]) -> bytes:
    buffer = io.BytesIO()
    with zipfile.ZipFile(buffer, "w", zipfile.ZIP_DEFLATED) as bundle:
        for name, data in members.items():
            bundle.writestr(name, data)
    return buffer.getvalue()


def test_an_archive_past_the_compression_ratio_is_413_before_anything_is_written(make_app, storage, monkeypatch):
    # 1 MB of zeros deflates to about 1 KB: far past a ratio of 20 once the exempt bytes are 0.
    api = TestClient(make_app(datasets.router, max_archive_ratio=20, archive_ratio_exempt_bytes=0))
    body = deflated_zip({"seq/frame_0000.exr": b"\x00" * 1_000_000})
    written = []
    monkeypatch.setattr(archives._Extractor, "file", lambda self, *args: written.append(args))
    error = assert_error(post_archive(api, body), 413, "payload_too_large", "declares 1000000 unpacked bytes",
                         "compression ratio")
    assert error["details"] == {"limit_bytes": 20 * len(body)}
    assert written == []  # refused from the zip's directory, before extracting
    assert_nothing_stored(storage)


def test_a_gzip_tar_past_the_compression_ratio_is_413(make_app, storage, tmp_path):
    api = TestClient(make_app(datasets.router, max_archive_ratio=20, archive_ratio_exempt_bytes=0))
    buffer = io.BytesIO()
    with tarfile.open(fileobj=buffer, mode="w:gz") as bundle:
        info = tarfile.TarInfo("seq/frame_0000.exr")
        info.size = 4_000_000
        bundle.addfile(info, io.BytesIO(b"\x00" * info.size))
    body = buffer.getvalue()
    assert_error(post_archive(api, body, content_type="application/gzip"), 413, "payload_too_large",
                 f"unpacks to more than {20 * len(body)} bytes")
    assert_nothing_stored(storage)


def test_the_unpacked_limit_is_the_ratio_within_the_exemption_and_the_cap():
    limit = archives.unpacked_limit
    assert limit(1000, max_bytes=10**9, max_ratio=20, exempt_bytes=0) == 20_000
    assert limit(1000, max_bytes=10**9, max_ratio=20, exempt_bytes=50_000) == 50_000
    assert limit(10**8, max_bytes=10**9, max_ratio=20, exempt_bytes=0) == 10**9


@pytest.mark.parametrize("member", ["../evil.exr", "seq/../../evil.exr", "/etc/evil.exr", "C:/evil.exr",
                                    "seq\\..\\evil.exr"])
def test_unsafe_member_paths_are_400_naming_the_member(api, storage, member):
    response = post_archive(api, zip_bytes({"seq/manifest.json": b"{}", member: b"x"}))
    error = assert_error(response, 400, "unsafe_archive_member", repr(member))
    assert error["details"] == {"member": member}
    assert_nothing_stored(storage)
    assert not (storage.root.parent / "evil.exr").exists()


def test_zip_symlink_is_400(api, storage):
    buffer = io.BytesIO()
    with zipfile.ZipFile(buffer, "w") as bundle:
        link = zipfile.ZipInfo("seq/frame_0000.exr")
        link.external_attr = (0o120777 << 16)  # what `zip --symlinks` writes
        bundle.writestr(link, "/etc/passwd")
    assert_error(post_archive(api, buffer.getvalue()), 400, "unsafe_archive_member", "'seq/frame_0000.exr'",
                 "symbolic link")
    assert_nothing_stored(storage)


@pytest.mark.parametrize("link_type, word", [(tarfile.SYMTYPE, "symbolic"), (tarfile.LNKTYPE, "hard")])
def test_tar_links_are_400(api, storage, link_type, word):
    buffer = io.BytesIO()
    with tarfile.open(fileobj=buffer, mode="w") as bundle:
        link = tarfile.TarInfo("seq/manifest.json")
        link.type, link.linkname = link_type, "/etc/passwd"
        bundle.addfile(link)
    response = post_archive(api, buffer.getvalue(), content_type="application/x-tar")
    assert_error(response, 400, "unsafe_archive_member", "'seq/manifest.json'", f"{word} link", "/etc/passwd")
    assert_nothing_stored(storage)


def test_sequence_folder_without_manifest_is_400_naming_it(api, storage, two_sequences, make_archive):
    (two_sequences / "seq_b" / "manifest.json").unlink()
    error = assert_error(post_archive(api, make_archive(two_sequences)), 400, "missing_manifest",
                         "sequence folder seq_b has no manifest.json")
    assert error["details"] == {"path": "seq_b"}
    assert_nothing_stored(storage)


def test_invalid_exr_is_400_naming_the_frame(api, storage, two_sequences, make_archive):
    (two_sequences / "seq_b" / "frame_0001.exr").write_bytes(b"v/1\x01 truncated")
    error = assert_error(post_archive(api, make_archive(two_sequences)), 400, "invalid_frame",
                         "seq_b/frame_0001.exr")
    assert error["details"]["path"] == "seq_b/frame_0001.exr"
    assert str(storage.root) not in error["message"]  # names the archive path, not the server's staging path
    assert_nothing_stored(storage)


def test_frame_not_matching_its_manifest_is_400(api, storage, tmp_path, two_sequences, tiny_frames,
                                                make_archive):
    stranger = tiny_frames(2, size=4, sequence="seq_a")[1]
    write_frame(two_sequences / "seq_a" / "frame_0001.exr", stranger)
    assert_error(post_archive(api, make_archive(two_sequences)), 400, "invalid_frame",
                 "seq_a/frame_0001.exr: resolution is (4, 4) but seq_a/manifest.json says (8, 8)")
    assert_nothing_stored(storage)


def test_files_that_are_not_frames_are_left_out_and_named_but_a_stray_exr_is_400(api, two_sequences, make_archive):
    (two_sequences / "notes.txt").write_text("hi")
    (two_sequences / "manifest.json").write_text('{"pipeline": "nuke", "shots": ["seq_a", "seq_b"]}')  # not ours
    (two_sequences / "seq_a" / "preview.jpg").write_bytes(b"jpeg")
    response = post_archive(api, make_archive(two_sequences), name="mixed")
    assert response.status_code == 201, response.text
    assert response.headers["X-Ignored-Files"] == "manifest.json, notes.txt, seq_a/preview.jpg"
    assert sorted(s["name"] for s in response.json()["sequences"]) == ["seq_a", "seq_b"]
    (two_sequences / "loose.exr").write_bytes(b"x")
    assert_error(post_archive(api, make_archive(two_sequences), name="stray"), 400, "invalid_dataset",
                 "loose.exr is not inside a sequence folder")


# --- adding to an existing dataset -------------------------------------------------------------------------


@pytest.fixture
def stored(api, two_sequences, make_archive):
    """Dataset 'tiny' holding seq_a and seq_b."""
    assert post_archive(api, make_archive(two_sequences), name="tiny").status_code == 201
    return "tiny"


def test_add_sequences_to_a_dataset(api, stored, tmp_path, tiny_sequence, make_archive):
    tiny_sequence(tmp_path / "more" / "seq_c", 4, seed=20)
    response = post_archive(api, make_archive(tmp_path / "more"), path="/datasets/tiny/sequences", split="test")
    assert response.status_code == 201, response.text
    assert response.headers["location"] == "/datasets/tiny"
    assert {s["name"]: (s["split"], s["frames"]) for s in response.json()["sequences"]} == {
        "seq_a": ("train", 2), "seq_b": ("train", 3), "seq_c": ("test", 4)}


def test_existing_sequence_name_is_409_unless_replace(api, storage, stored, tmp_path, tiny_sequence, make_archive):
    tiny_sequence(tmp_path / "again" / "seq_a", 5, seed=30)
    body = make_archive(tmp_path / "again")
    error = assert_error(post_archive(api, body, path="/datasets/tiny/sequences"), 409, "sequence_exists",
                         "seq_a", "replace=true")
    assert error["details"] == {"dataset": "tiny", "sequences": ["seq_a"]}
    assert api.get("/datasets/tiny").json()["sequences"][0]["frames"] == 2
    response = post_archive(api, body, path="/datasets/tiny/sequences", replace="true", split="validation")
    assert response.status_code == 201, response.text
    assert response.json()["sequences"][0] | {"buffers": None} == {
        "name": "seq_a", "split": "validation", "scene": "cornell", "frames": 5, "width": 8, "height": 8,
        "scales": [1], "buffers": None, "camera_cuts": [0]}
    assert [p.name for p in storage.staging.iterdir() if p.name != "locks"] == []


def test_failed_add_keeps_the_stored_dataset_unchanged(api, storage, stored, tmp_path, tiny_sequence,
                                                       make_archive):
    before = {p.relative_to(storage.datasets): p.read_bytes() for p in storage.datasets.rglob("*") if p.is_file()}
    tiny_sequence(tmp_path / "more" / "seq_c", 2)
    tiny_sequence(tmp_path / "more" / "seq_d", 2)
    (tmp_path / "more" / "seq_d" / "frame_0000.exr").write_bytes(b"not an exr")
    assert_error(post_archive(api, make_archive(tmp_path / "more"), path="/datasets/tiny/sequences",
                              replace="true"), 400, "invalid_frame", "seq_d/frame_0000.exr")
    after = {p.relative_to(storage.datasets): p.read_bytes() for p in storage.datasets.rglob("*") if p.is_file()}
    assert after == before
    assert [p.name for p in storage.staging.iterdir() if p.name != "locks"] == []


# --- unknown datasets, delete, auth ------------------------------------------------------------------------


@pytest.mark.parametrize("method, path", [("get", "/datasets/nope"), ("delete", "/datasets/nope"),
                                          ("post", "/datasets/nope/sequences")])
def test_unknown_dataset_is_404(api, method, path):
    response = getattr(api, method)(path, **({"content": b"PK"} if method == "post" else {}))
    assert_error(response, 404, "not_found", "dataset 'nope' does not exist")


def test_invalid_dataset_id_in_the_path_is_400(api):
    assert_error(api.get("/datasets/.hidden"), 400, "invalid_name", "'.hidden' is not a valid id")


def test_delete_removes_the_dataset(api, storage, stored):
    assert api.delete("/datasets/tiny").status_code == 204
    assert_error(api.get("/datasets/tiny"), 404, "not_found")
    assert api.get("/datasets").json() == []
    assert list(storage.datasets.iterdir()) == []


def test_api_key_is_required_when_configured(make_app):
    api = TestClient(make_app(datasets.router, api_key="secret"))
    assert_error(api.get("/datasets"), 401, "unauthorized", "X-API-Key")
    assert api.get("/datasets", headers={"X-API-Key": "secret"}).status_code == 200


# --- frame-by-frame uploads --------------------------------------------------------------------------------


def post_frame(api, body: bytes, dataset="live", sequence="cam_0", **params):
    return api.post(f"/datasets/{dataset}/sequences/{sequence}/frames", content=body,
                    headers={"Content-Type": "image/x-exr"}, params=params)


def test_frames_one_by_one_then_commit_creates_the_dataset(api, storage, tmp_path, tiny_frames):
    frames = tiny_frames(3, cuts=(0, 2))
    response = post_frame(api, frame_bytes(tmp_path, frames[0]), split="validation", scene="street", scales="1")
    assert response.status_code == 200, response.text
    assert response.json() == {"dataset": "live", "sequence": "cam_0", "split": "validation", "scene": "street",
                               "frames": 1, "next_frame_index": 1, "width": 8, "height": 8, "scales": [1],
                               "buffers": BUFFERS}
    for frame in frames[1:]:
        assert post_frame(api, frame_bytes(tmp_path, frame)).status_code == 200
    assert api.get("/datasets/live/sequences/cam_0/frames").json()["next_frame_index"] == 3
    assert_error(api.get("/datasets/live"), 404, "not_found")  # nothing visible before the commit

    response = api.post("/datasets/live/sequences/cam_0/commit")
    assert response.status_code == 201, response.text
    assert response.headers["location"] == "/datasets/live"
    assert response.json()["sequences"] == [{
        "name": "cam_0", "split": "validation", "scene": "street", "frames": 3, "width": 8, "height": 8,
        "scales": [1], "buffers": BUFFERS, "camera_cuts": [0, 2]}]
    assert_error(api.get("/datasets/live/sequences/cam_0/frames"), 404, "not_found", "no frames of sequence")
    assert [p.name for p in (storage.staging / "sequences" / "live").iterdir()] == []


def test_frame_out_of_order_is_409(api, tmp_path, tiny_frames):
    frames = tiny_frames(3)
    assert_error(post_frame(api, frame_bytes(tmp_path, frames[1])), 409, "frame_out_of_order",
                 "frame_index is 1, expected 0")
    assert post_frame(api, frame_bytes(tmp_path, frames[0])).status_code == 200
    error = assert_error(post_frame(api, frame_bytes(tmp_path, frames[0])), 409, "frame_out_of_order")
    assert error["details"] == {"expected": 1, "received": 0}


def test_frame_not_continuing_the_sequence_is_400(api, tmp_path, tiny_frames):
    assert post_frame(api, frame_bytes(tmp_path, tiny_frames(1)[0])).status_code == 200
    larger = tiny_frames(2, size=4)[1]
    assert_error(post_frame(api, frame_bytes(tmp_path, larger)), 400, "invalid_frame",
                 "resolution 4x4 differs from the first frame's 8x8")
    other_scales = tiny_frames(2, scales=(1, 2))[1]
    assert_error(post_frame(api, frame_bytes(tmp_path, other_scales)), 400, "invalid_frame",
                 "reference scales [1, 2] differ from the first frame's [1]")
    assert_error(post_frame(api, frame_bytes(tmp_path, tiny_frames(2)[1]), split="test"), 409, "split_mismatch")


def test_invalid_frame_uploads_are_400(api, tmp_path, tiny_frames):
    assert_error(post_frame(api, b"definitely not an EXR"), 400, "invalid_frame",
                 "frame upload to live/cam_0: not an OpenEXR file")
    assert_error(post_frame(api, frame_bytes(tmp_path, tiny_frames(1, sequence="other")[0])), 400,
                 "invalid_frame", "the frame's 'sequence' header says 'other', not 'cam_0'")
    assert_error(post_frame(api, frame_bytes(tmp_path, tiny_frames(1)[0]), scales="1,2"), 400, "invalid_frame",
                 "reference scales [1] are not the requested [1, 2]")
    assert_error(post_frame(api, b"x", scales="two"), 400, "invalid_scales", "'two'")
    assert_error(post_frame(api, b"x", sequence="a b"), 400, "invalid_name", "sequence name 'a b'")
    response = api.post("/datasets/live/sequences/cam_0/frames", content=b"x", headers={"Content-Type": "image/png"})
    assert_error(response, 415, "unsupported_media_type")
    assert_error(api.get("/datasets/live/sequences/cam_0/frames"), 404, "not_found")


def test_too_large_frame_is_413(make_app, tmp_path, tiny_frames):
    api = TestClient(make_app(datasets.router, max_frame_bytes=100))
    assert_error(post_frame(api, frame_bytes(tmp_path, tiny_frames(1)[0])), 413, "payload_too_large",
                 "the frame is")


def test_commit_into_an_existing_dataset_409_then_replace(api, stored, tmp_path, tiny_frames):
    for frame in tiny_frames(2, sequence="seq_a"):  # frames naming their sequence are stored as sent
        assert post_frame(api, frame_bytes(tmp_path, frame), dataset="tiny", sequence="seq_a").status_code == 200
    assert_error(api.post("/datasets/tiny/sequences/seq_a/commit"), 409, "sequence_exists", "seq_a")
    # the staged frames survive the refused commit
    assert api.get("/datasets/tiny/sequences/seq_a/frames").json()["frames"] == 2
    response = api.post("/datasets/tiny/sequences/seq_a/commit", params={"replace": "true"})
    assert response.status_code == 201, response.text
    assert [s["name"] for s in response.json()["sequences"]] == ["seq_a", "seq_b"]


def test_commit_or_discard_of_nothing_is_404_and_discard_drops_frames(api, tmp_path, tiny_frames):
    assert_error(api.post("/datasets/live/sequences/cam_0/commit"), 404, "not_found", "no frames of sequence")
    assert_error(api.delete("/datasets/live/sequences/cam_0/frames"), 404, "not_found")
    assert post_frame(api, frame_bytes(tmp_path, tiny_frames(1)[0])).status_code == 200
    assert api.delete("/datasets/live/sequences/cam_0/frames").status_code == 204
    assert_error(api.post("/datasets/live/sequences/cam_0/commit"), 404, "not_found")


# --- OpenAPI -----------------------------------------------------------------------------------------------


def test_openapi_documents_bodies_errors_and_examples(api):
    document = api.get("/openapi.json").json()
    upload = document["paths"]["/datasets"]["post"]
    assert "application/zip" in upload["requestBody"]["content"]
    assert {"201", "400", "409", "413", "415"} <= set(upload["responses"])
    frames = document["paths"]["/datasets/{dataset_id}/sequences/{sequence}/frames"]["post"]
    assert "image/x-exr" in frames["requestBody"]["content"]
    schemas = document["components"]["schemas"]
    for name in ("DatasetDetail", "DatasetSummary", "SequenceInfo", "SplitSummary", "StagedSequence"):
        assert schemas[name].get("examples"), name


def test_a_decompression_bomb_frame_upload_is_413(make_app, storage):
    from tests.builders import zero_bomb

    api = TestClient(make_app(datasets.router, max_frame_pixels=1_000_000))
    error = assert_error(post_frame(api, zero_bomb(1024, 1024)), 413, "frame_too_large",
                         "frame upload to live/cam_0: declares 1024x1024 = 1048576 pixels")
    assert error["details"]["limit_pixels"] == 1_000_000
    assert api.get("/datasets/live/sequences/cam_0/frames").status_code == 404


def test_an_archive_holding_a_decompression_bomb_is_413_before_frames_are_decoded(make_app, storage, two_sequences,
                                                                                    make_archive, monkeypatch):
    import model.io.exr
    from tests.builders import zero_bomb

    (two_sequences / "seq_b" / "frame_0001.exr").write_bytes(zero_bomb(1024, 1024))
    api = TestClient(make_app(datasets.router, max_frame_pixels=1_000_000))
    decoded = []
    monkeypatch.setattr(model.io.exr, "_read_coalesced", lambda *args: decoded.append(args))
    error = assert_error(post_archive(api, make_archive(two_sequences)), 413, "frame_too_large",
                         "seq_b/frame_0001.exr: declares 1024x1024")
    assert error["details"]["path"] == "seq_b/frame_0001.exr"
    assert decoded == []
    assert_nothing_stored(storage)


@pytest.mark.parametrize(("manifest", "fragment"), [
    (b"[" * 100_000, "manifest.json: not valid JSON here (nested too deeply)"),
    (b'{"format": ' + b"1" * 5000 + b"}", "manifest.json: not valid JSON here"),
])
def test_a_manifest_the_json_parser_refuses_is_400_not_500(api, storage, manifest, fragment):
    body = zip_bytes({"seq/manifest.json": manifest, "seq/frame_0000.exr": b"x"})
    assert_error(post_archive(api, body), 400, "invalid_dataset", fragment)
    assert_nothing_stored(storage)


def test_requests_on_unknown_ids_leave_no_lock_files(api, storage):
    for method, path in (("DELETE", "/datasets/ghost"), ("GET", "/datasets/ghost"),
                         ("DELETE", "/datasets/ghost/sequences/cam/frames"),
                         ("POST", "/datasets/ghost/sequences/cam/commit")):
        assert api.request(method, path).status_code == 404, (method, path)
    locks = storage.staging / "locks"
    assert not locks.exists() or list(locks.iterdir()) == []


def test_abandoned_frame_uploads_expire(make_app, storage, tmp_path, tiny_frames):
    import os
    import time

    api = TestClient(make_app(datasets.router, staged_upload_ttl_seconds=3600))
    assert post_frame(api, frame_bytes(tmp_path, tiny_frames(1)[0]), sequence="old").status_code == 200
    assert post_frame(api, frame_bytes(tmp_path, tiny_frames(1)[0]), sequence="fresh").status_code == 200
    state = storage.staging / "sequences" / "live" / "old.json"
    long_ago = time.time() - 3601
    os.utime(state, (long_ago, long_ago))  # untouched for longer than the TTL
    assert staged.expire_staged_uploads(storage, 3600) == ["live/old"]
    assert api.get("/datasets/live/sequences/old/frames").status_code == 404
    assert not (storage.staging / "sequences" / "live" / "old").exists()
    assert api.get("/datasets/live/sequences/fresh/frames").json()["frames"] == 1
    # Uploading a frame sweeps too: one more abandoned upload goes with the next frame of any sequence.
    fresh = storage.staging / "sequences" / "live" / "fresh.json"
    os.utime(fresh, (long_ago, long_ago))
    assert post_frame(api, frame_bytes(tmp_path, tiny_frames(1)[0]), sequence="other").status_code == 200
    assert api.get("/datasets/live/sequences/fresh/frames").status_code == 404
