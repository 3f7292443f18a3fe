"""client.rest.DenoiserClient against an in-memory fake of the REST contract (tests/client/fake_api.py)."""

from __future__ import annotations

import io
import tarfile
import zipfile

import httpx
import numpy as np
import pytest

from model.io.dataset import Dataset
from model.io.exr import read_frame, write_frame
from client.rest import (
    ApiClientError,
    DenoiserClient,
    ServerUnreachable,
    archive_media_type,
    decode_rgb_exr,
    folder_members,
    frame_bytes,
    pack_folder,
)
from tests.builders import closed_port, make_frame, uncut_frame, write_frame_sequence

from .fake_api import FakeApi, error


@pytest.fixture
def api():
    return FakeApi()


@pytest.fixture
def client(api):
    with api.client() as client:
        yield client


# --- errors --------------------------------------------------------------------------------------------------


def test_error_shape_becomes_api_client_error(client):
    with pytest.raises(ApiClientError) as info:
        client.get_dataset("missing")
    assert (info.value.status, info.value.code) == (404, "not_found")
    assert info.value.message == "dataset 'missing' does not exist"
    assert info.value.is_client_error
    assert str(info.value) == "404 not_found: dataset 'missing' does not exist"


def test_details_are_kept_and_non_json_errors_still_raise():
    def handler(request):
        if request.method == "POST":
            return error(422, "invalid_request", "invalid request: params.steps: too small",
                         [{"location": "body.params.steps", "message": "too small"}])
        return httpx.Response(502, text="<html>Bad Gateway</html>")

    with DenoiserClient("http://fake.test", transport=httpx.MockTransport(handler)) as client:
        with pytest.raises(ApiClientError) as info:
            client.submit_job("train", {"steps": 0})
        assert info.value.details == [{"location": "body.params.steps", "message": "too small"}]
        with pytest.raises(ApiClientError) as info:
            client.list_jobs()
    assert (info.value.status, info.value.code) == (502, "http_502")
    assert "Bad Gateway" in info.value.message and not info.value.is_client_error


def test_api_key_is_sent_and_its_absence_is_a_401():
    api = FakeApi(api_key="s3cret")
    with api.client() as anonymous:
        with pytest.raises(ApiClientError) as info:
            anonymous.list_datasets()
        assert info.value.status == 401 and "X-API-Key" in info.value.message
        assert anonymous.health() == {"status": "ok"}  # /health needs no key
    with api.client(api_key="s3cret") as client:
        assert client.list_datasets() == []


def test_connection_refused_names_the_url():
    url = f"http://127.0.0.1:{closed_port()}"
    with DenoiserClient(url, timeout=2) as client:
        with pytest.raises(ServerUnreachable) as info:
            client.list_jobs()
    assert url in str(info.value) and "refused" in str(info.value)


def test_the_url_is_the_callers_else_the_local_default_never_the_environment(monkeypatch):
    # The embedding program chooses the address (the CLI passes its settings'); the library reads no variables.
    monkeypatch.setenv("DENOISER_URL", "http://elsewhere.test:9000/")
    assert DenoiserClient().url == "http://127.0.0.1:8000"
    assert DenoiserClient("http://there.test:9000/").url == "http://there.test:9000"


def test_ids_cannot_address_another_route(client):
    with pytest.raises(ValueError, match="not a valid identifier"):
        client.get_job("../datasets")


def test_list_envelopes_are_unwrapped():
    transport = httpx.MockTransport(lambda request: httpx.Response(200, json={"items": [{"id": "a"}], "total": 1}))
    with DenoiserClient("http://fake.test", transport=transport) as client:
        assert client.list_jobs() == [{"id": "a"}]


# --- datasets ------------------------------------------------------------------------------------------------


def test_upload_packs_only_what_the_manifests_list(api, client, tmp_path):
    root = tmp_path / "demo"
    dataset = Dataset.create(root)
    write_frame_sequence(root, "seq_a", 2)
    dataset.add_sequence_dir("seq_a", "validation")
    (root / "preview.png").write_bytes(b"not part of the dataset")
    (root / ".seq_b.1234.partial").mkdir()
    (root / ".seq_b.1234.partial" / "frame_0000.exr").write_bytes(b"half written")

    skipped = []
    record = client.upload_dataset(root, name="demo", skipped=skipped)

    assert record["id"] == "demo"
    params, content_type, length, members = api.uploads[-1]
    assert params == {"split": "train", "name": "demo"}
    assert content_type == "application/x-tar" and int(length) > 0  # streamed from a file of known size
    assert sorted(members) == ["demo/manifest.json", "demo/seq_a/frame_0000.exr", "demo/seq_a/frame_0001.exr",
                               "demo/seq_a/manifest.json"]
    assert skipped == [".seq_b.1234.partial/frame_0000.exr", "preview.png"]


def test_upload_of_one_sequence_folder_and_of_a_folder_of_sequences(api, client, tmp_path):
    sequence = write_frame_sequence(tmp_path / "loose", "seq_a", 2)
    write_frame_sequence(tmp_path / "loose", "seq_b", 1, seed=5)

    client.upload_dataset(sequence, split="test")
    assert api.uploads[-1][0] == {"split": "test"}
    assert sorted(api.uploads[-1][3]) == ["seq_a/frame_0000.exr", "seq_a/frame_0001.exr", "seq_a/manifest.json"]

    client.upload_dataset(tmp_path / "loose")
    assert sorted(api.uploads[-1][3]) == ["loose/seq_a/frame_0000.exr", "loose/seq_a/frame_0001.exr",
                                          "loose/seq_a/manifest.json", "loose/seq_b/frame_0000.exr",
                                          "loose/seq_b/manifest.json"]


def test_an_archive_is_sent_as_it_is(api, client, tmp_path):
    archive = tmp_path / "upload.zip"
    with zipfile.ZipFile(archive, "w") as zipped:
        zipped.writestr("seq_a/manifest.json", "{}")
    client.upload_dataset(archive)
    assert api.uploads[-1][1] == "application/zip" and api.uploads[-1][3] == ["seq_a/manifest.json"]
    assert archive_media_type(tmp_path / "x.tar.gz") == "application/gzip"
    assert archive_media_type(tmp_path / "x.bin") == "application/octet-stream"


def test_upload_errors(api, client, tmp_path):
    with pytest.raises(FileNotFoundError, match="nothing to upload"):
        client.upload_dataset(tmp_path)  # an empty folder
    with pytest.raises(FileNotFoundError, match="no such file"):
        client.upload_dataset(tmp_path / "missing.zip")
    write_frame_sequence(tmp_path / "d", "seq_a", 1)
    client.upload_dataset(tmp_path / "d", name="taken")
    with pytest.raises(ApiClientError) as info:
        client.upload_dataset(tmp_path / "d", name="taken")
    assert (info.value.status, info.value.code) == (409, "conflict")


def test_pack_folder_writes_an_uncompressed_tar(tmp_path):
    write_frame_sequence(tmp_path / "d", "seq_a", 1)
    left_out = pack_folder(tmp_path / "d" / "seq_a", tmp_path / "out.tar")
    assert left_out == []
    with tarfile.open(tmp_path / "out.tar", "r:") as tar:  # "r:" fails on a compressed archive
        assert sorted(tar.getnames()) == ["seq_a/frame_0000.exr", "seq_a/manifest.json"]
    members, _ = folder_members(tmp_path / "d" / "seq_a")
    assert [m.name for m in members] == ["manifest.json", "frame_0000.exr"]


def test_datasets_list_get_delete(client, tmp_path):
    write_frame_sequence(tmp_path / "d", "seq_a", 1)
    client.upload_dataset(tmp_path / "d", name="one")
    assert [d["id"] for d in client.list_datasets()] == ["one"]
    assert client.get_dataset("one")["sequences"][0]["name"] == "seq_a"
    client.delete_dataset("one")
    assert client.list_datasets() == []


# --- jobs ----------------------------------------------------------------------------------------------------


def test_wait_job_reports_changes_and_backs_off_while_nothing_moves(api):
    sleeps = []
    with api.client(sleep=sleeps.append) as client:
        job = client.submit_job("train", {"method": "wskpn:xs", "steps": 4}, device="gpu")
        assert job["state"] == "queued" and job["queue"] == "gpu"
        seen = []
        final = client.wait_job(job["id"], seen.append, interval=0.5, max_interval=1.0, backoff=1.5)
    assert final["state"] == "succeeded" and final["result"] == {"psnr": 31.5}
    # One callback per change: queued, running 1/4, running 3/4, succeeded; the repeats of 1/4 call nothing.
    assert [(j["state"], j["progress"]["current"]) for j in seen] == [
        ("queued", 0), ("running", 1), ("running", 3), ("succeeded", 4)]
    # The wait grows while the job sits at 1/4 (0.75, then capped at 1.0) and drops back when it moves.
    assert sleeps == [0.5, 0.5, 0.75, 1.0, 0.5]


def test_follow_job_ends_on_failure_and_cancellation(api):
    api.script = [("running", {"current": 1, "total": 2}), ("failed", {"current": 1, "total": 2})]
    api.final_error = {"code": "worker_error", "message": "out of memory"}
    with api.client() as client:
        job = client.submit_job("train", {})
        final = client.follow_job(job["id"], lambda j: None)
        assert final["state"] == "failed" and final["error"]["message"] == "out of memory"
        job = client.submit_job("evaluate", {})
        client.cancel_job(job["id"])
        assert client.wait_job(job["id"])["state"] == "cancelled"
        with pytest.raises(ApiClientError) as info:
            client.cancel_job(job["id"])
    assert (info.value.status, info.value.code) == (409, "conflict")


def test_wait_job_times_out_without_touching_the_job(api):
    api.script = [("running", {"current": 1, "total": 9})] * 50
    now = [0.0]

    def sleep(seconds):
        now[0] += seconds

    with api.client(sleep=sleep, clock=lambda: now[0]) as client:
        job = client.submit_job("train", {})
        with pytest.raises(TimeoutError, match=f"job {job['id']} is still running after 3 s"):
            client.wait_job(job["id"], timeout=3, interval=0.5, max_interval=1.0)
    assert now[0] <= 3
    assert api.jobs[job["id"]]["state"] == "running"


def test_wait_job_rides_out_a_server_restart_but_not_a_dead_server(api):
    down = {"polls": 2}

    def flaky(request):
        if request.method == "GET" and down["polls"] > 0:
            down["polls"] -= 1
            raise httpx.ConnectError("[Errno 111] Connection refused")
        return api.handle(request)

    sleeps = []
    with DenoiserClient("http://fake.test", transport=httpx.MockTransport(flaky), sleep=sleeps.append) as client:
        job = client.submit_job("train", {})
        assert client.wait_job(job["id"], interval=0.5, max_interval=2.0)["state"] == "succeeded"
        assert sleeps[:2] == [2.0, 2.0]  # the longest interval while the server is away
        job = client.submit_job("train", {})
        down["polls"] = 10
        with pytest.raises(ServerUnreachable, match="refused"):
            client.wait_job(job["id"], unreachable_retries=3)
    assert down["polls"] == 6  # the first try and 3 retries


def test_submit_errors_and_job_listing(api, client):
    with pytest.raises(ApiClientError) as info:
        client.submit_job("paint", {})
    assert info.value.status == 422 and "kind" in info.value.message
    with pytest.raises(ApiClientError) as info:
        client.submit_job("train", {"dataset": "nope"})
    assert info.value.status == 404 and "nope" in info.value.message
    client.submit_job("train", {})
    client.submit_job("evaluate", {})
    assert [j["kind"] for j in client.list_jobs(kind="evaluate")] == ["evaluate"]
    assert len(client.list_jobs(state="queued")) == 2
    with pytest.raises(ApiClientError) as info:
        client.get_job("job-9999")
    assert info.value.status == 404


def test_job_logs(api, client):
    job = client.submit_job("train", {})
    assert client.job_logs(job["id"], lines=3) == ["line 7", "line 8", "line 9"]


def test_download_results_extracts_the_zip(api, client, tmp_path):
    buffer = io.BytesIO()
    with zipfile.ZipFile(buffer, "w") as zipped:
        zipped.writestr("seq_a/frame_0000.exr", b"exr-0")
        zipped.writestr("seq_a/frame_0001.exr", b"exr-1")
    api.results_zip = buffer.getvalue()
    job = client.submit_job("infer", {})
    files = client.download_results(job["id"], tmp_path / "out")
    assert sorted(p.relative_to(tmp_path / "out").as_posix() for p in files) == [
        "seq_a/frame_0000.exr", "seq_a/frame_0001.exr"]
    assert (tmp_path / "out" / "seq_a" / "frame_0001.exr").read_bytes() == b"exr-1"
    assert sorted(p.name for p in (tmp_path / "out").iterdir()) == ["seq_a"]  # the zip itself is gone
    kept = client.download_results(job["id"], tmp_path / "zip", extract=False)
    assert zipfile.is_zipfile(kept[0])


def test_download_results_refuses_members_outside_the_folder(api, client, tmp_path):
    buffer = io.BytesIO()
    with zipfile.ZipFile(buffer, "w") as zipped:
        zipped.writestr("../escape.exr", b"x")
    api.results_zip = buffer.getvalue()
    job = client.submit_job("infer", {})
    with pytest.raises(ValueError, match="outside"):
        client.download_results(job["id"], tmp_path / "out")
    assert not (tmp_path / "escape.exr").exists()


def test_download_results_error_is_raised_and_leaves_no_file(api, client, tmp_path):
    job = client.submit_job("infer", {})
    with pytest.raises(ApiClientError) as info:
        client.download_results(job["id"], tmp_path / "out")
    assert info.value.status == 409
    assert list((tmp_path / "out").iterdir()) == []


# --- models --------------------------------------------------------------------------------------------------


def test_models_and_aliases(api, client):
    assert [m["name"] for m in client.list_models()] == ["wskpn-xs"]
    assert [v["version"] for v in client.get_model("wskpn-xs")["versions"]] == ["1", "2"]
    client.set_alias("wskpn-xs", "champion", 2)
    assert api.models["wskpn-xs"]["aliases"]["champion"] == "2"  # the version is sent as a string
    with pytest.raises(ApiClientError) as info:
        client.set_alias("wskpn-xs", "champion", 7)
    assert info.value.status == 404 and "version '7'" in info.value.message


# --- sessions ------------------------------------------------------------------------------------------------


def test_send_frame_returns_rgb_and_parsed_headers(api, client, tmp_path):
    session = client.create_session("wskpn-xs", alias="champion")
    assert session["model"]["version"] == "1"
    frame = uncut_frame(1, 0)
    rgb, info = client.send_frame(session["id"], frame)
    assert rgb.dtype == np.float32 and rgb.shape == (4, 6, 3)
    np.testing.assert_array_equal(rgb, frame.color * 0.5)
    assert (info.frame_index, info.inference_ms, info.server_ms, info.history) == (0, 1.5, 2.25, "started")
    assert info.round_trip_ms > 0 and info.headers["X-History"] == "started"
    # A path and raw bytes work too; both without the references, which the server ignores.
    path = write_frame(tmp_path / "f1.exr", uncut_frame(2, 1))
    _, info = client.send_frame(session["id"], path)
    assert info.history == "continued"
    _, info = client.send_frame(session["id"], frame_bytes(uncut_frame(3, 5)))
    assert info.history == "reset-gap"
    with pytest.raises(ApiClientError) as info:
        client.send_frame(session["id"], uncut_frame(4, 2))
    assert (info.value.status, info.value.code) == (409, "frame_out_of_order")


def test_frame_bytes_drops_references_unless_a_file_is_sent_as_it_is(tmp_path):
    frame = make_frame(0, scales=(1, 2))
    path = write_frame(tmp_path / "frame.exr", frame)
    stripped = tmp_path / "stripped.exr"
    stripped.write_bytes(frame_bytes(path))
    assert frame_bytes(path, strip_references=False) == path.read_bytes()
    assert read_frame(stripped).scales == () and read_frame(path).scales == (1, 2)
    assert stripped.stat().st_size < path.stat().st_size
    # A model FrameBundle is encoded without its references, with the same render buffers and header.
    again = read_frame(_written(tmp_path, frame_bytes(frame)))
    np.testing.assert_array_equal(again.color, frame.color)
    np.testing.assert_array_equal(again.motion, frame.motion)
    assert (again.jitter, again.frame_index, again.sequence, again.scales) == (frame.jitter, frame.frame_index,
                                                                            frame.sequence, ())


def _written(tmp_path, data: bytes):
    path = tmp_path / "written.exr"
    path.write_bytes(data)
    return path


def test_session_errors(api, client):
    with pytest.raises(ValueError, match="not both"):
        client.create_session("wskpn-xs", version="1", alias="champion")
    with pytest.raises(ApiClientError) as info:
        client.create_session("nope")
    assert info.value.status == 404
    session = client.create_session("wskpn-xs", on_gap="reject")
    client.send_frame(session["id"], uncut_frame(0, 0))
    with pytest.raises(ApiClientError) as info:
        client.send_frame(session["id"], uncut_frame(0, 3))
    assert (info.value.status, info.value.code) == (409, "frame_gap")
    client.delete_session(session["id"])
    with pytest.raises(ApiClientError) as info:
        client.get_session(session["id"])
    assert info.value.status == 404


def test_stream_sequence_writes_one_exr_per_frame(api, tmp_path):
    api.output_scale = 2
    sequence = write_frame_sequence(tmp_path / "data", "seq_a", 3, scales=(1, 2))
    seen = []
    with api.client() as client:
        session = client.create_session("wskpn-xs", version="2")
        summary = client.stream_sequence(session["id"], sequence, tmp_path / "out",
                                         on_frame=lambda info, path: seen.append((info.history, path.name)))
    assert seen == [("started", "frame_0000.exr"), ("continued", "frame_0001.exr"), ("continued", "frame_0002.exr")]
    assert [p.name for p in sorted((tmp_path / "out").iterdir())] == ["frame_0000.exr", "frame_0001.exr",
                                                                      "frame_0002.exr"]
    for index, path in enumerate(summary.files):
        source = read_frame(sequence / f"frame_{index:04d}.exr")
        rgb = decode_rgb_exr(path.read_bytes())
        assert rgb.shape == (8, 12, 3)  # scale 2 x the 6x4 render resolution
        np.testing.assert_array_equal(rgb[::2, ::2], source.color * 0.5)
    numbers = summary.as_dict()
    assert numbers["frames"] == 3 and numbers["median_inference_ms"] == 1.5 and numbers["median_server_ms"] == 2.25
    assert numbers["history"] == {"started": 1, "continued": 2}


def test_stream_sequence_sends_files_as_they_are_when_asked(api, tmp_path):
    sequence = write_frame_sequence(tmp_path / "data", "seq_a", 2, scales=(1,))
    with api.client() as client:
        session = client.create_session("wskpn-xs")
        summary = client.stream_sequence(session["id"], sequence, tmp_path / "out", strip_references=False)
    assert len(summary.files) == 2 and summary.frames[1].history == "continued"


def test_decode_rgb_exr_refuses_what_is_not_an_exr():
    with pytest.raises(ValueError, match="not an OpenEXR file"):
        decode_rgb_exr(b"{\"error\": 1}")


def test_a_stored_frame_with_nan_is_sent_for_the_session_to_repair(tmp_path):
    # A renderer's file with a stray NaN: the strict reader refuses it, the client sends it (the session repairs).
    import OpenEXR

    from model.io.exr import _frame_parts, read_frame_bytes
    from model.io.frames import FrameError
    from client.rest import frame_bytes

    frame = make_frame()
    frame.color[1, 2, 0] = np.nan
    frame.diffuse[1, 2, 0] = np.nan
    path = tmp_path / "frame_0003.exr"
    OpenEXR.File(_frame_parts(frame, half=False)).write(str(path))
    with pytest.raises(FrameError, match="not finite"):
        read_frame(path)
    sent = read_frame_bytes(frame_bytes(path), sanitizable=True)
    assert np.isnan(sent.color[1, 2, 0]) and sent.references == {}


def test_the_client_sends_the_owner_token_of_the_sessions_it_created():
    seen = []

    def handler(request):
        seen.append((request.method, request.url.path, request.headers.get("x-session-token")))
        if request.method == "POST" and request.url.path == "/sessions":
            return httpx.Response(201, json={"id": "a" * 32, "token": "tok"})
        if request.method == "DELETE":
            return httpx.Response(204)
        return httpx.Response(200, json={"id": "a" * 32})

    with DenoiserClient("http://fake.test", transport=httpx.MockTransport(handler)) as client:
        session = client.create_session("m")
        client.get_session(session["id"])
        client.reset_session(session["id"])
        client.delete_session(session["id"])
        client.get_session("b" * 32)  # not one it created: no token
    assert [token for _, _, token in seen] == [None, "tok", "tok", "tok", None]
