"""The CLI's client subcommands (and serve / worker / mlflow-ui): exit statuses, messages, --param parsing."""

from __future__ import annotations

import argparse
import io
import json
import sys
import shutil
import zipfile

import pytest

from cli.main import UsageError, main
from cli.commands import client as client_commands
from cli.commands import serve as serve_commands
from cli.commands.client import collect_params, parse_param
from tests.builders import closed_port, write_frame_sequence

from tests.client.fake_api import FakeApi


@pytest.fixture
def api(monkeypatch):
    """Every client subcommand talks to this fake; the URL and key the command resolved are recorded."""
    fake = FakeApi()
    fake.resolved = []
    resolve = client_commands._client

    def fake_client(args):
        with resolve(args) as real:
            fake.resolved.append((real.url, real._http.headers.get("X-API-Key")))
        return fake.client()

    monkeypatch.setattr(client_commands, "_client", fake_client)
    return fake


# --- reaching the server -------------------------------------------------------------------------------------


@pytest.mark.parametrize("argv", [["jobs"], ["models"], ["job", "j1"], ["alias", "m", "champion", "1"],
                                  ["submit", "train", "--param", "steps=1"]])
def test_connection_refused_exits_2_naming_the_url(argv, capsys):
    url = f"http://127.0.0.1:{closed_port()}"
    assert main(argv + ["--url", url, "--timeout", "2"]) == 2
    err = capsys.readouterr().err
    assert f"cannot reach the denoiser service at {url}" in err and "denoiser serve" in err


def test_url_and_key_come_from_options_then_settings(api, monkeypatch):
    from core.settings import get_settings

    monkeypatch.setenv("DENOISER_URL", "http://env.test:1234")
    monkeypatch.setenv("DENOISER_API_KEY", "from-env")
    get_settings.cache_clear()
    assert main(["jobs"]) == 0
    assert main(["jobs", "--url", "http://option.test:9", "--api-key", "from-option"]) == 0
    monkeypatch.delenv("DENOISER_URL")
    monkeypatch.delenv("DENOISER_API_KEY")
    get_settings.cache_clear()
    assert main(["jobs"]) == 0
    assert api.resolved == [("http://env.test:1234", "from-env"), ("http://option.test:9", "from-option"),
                            ("http://127.0.0.1:8000", None)]


def test_server_4xx_exits_2_with_the_server_message(api, capsys):
    assert main(["job", "job-404"]) == 2
    assert "the server refused the request (404 not_found): job 'job-404' does not exist" in capsys.readouterr().err
    assert main(["submit", "train", "--param", "dataset=nope"]) == 2
    assert "dataset 'nope' does not exist" in capsys.readouterr().err
    assert main(["alias", "wskpn-xs", "champion", "9"]) == 2
    assert "has no version '9'" in capsys.readouterr().err


def test_unauthorized_exits_2(api, capsys):
    api.api_key = "s3cret"
    assert main(["jobs"]) == 2
    assert "401 unauthorized" in capsys.readouterr().err


def test_server_5xx_exits_1(api, monkeypatch, capsys):
    from tests.client.fake_api import error

    monkeypatch.setattr(api, "list_jobs", lambda request: error(500, "internal_error", "internal error: boom"))
    assert main(["jobs"]) == 1
    assert "server error (500 internal_error): internal error: boom" in capsys.readouterr().err


# --- --param parsing -----------------------------------------------------------------------------------------


@pytest.mark.parametrize("text, expected", [
    ("steps=200", ("steps", 200)),
    ("lr=1e-3", ("lr", 0.001)),
    ("half=true", ("half", True)),
    ("method=wskpn:xs", ("method", "wskpn:xs")),
    ('scenes=["glass","kitchen"]', ("scenes", ["glass", "kitchen"])),
    ('name="123"', ("name", "123")),
    ("register_as=", ("register_as", "")),
    ("note=a=b", ("note", "a=b")),
    ("limit=null", ("limit", None)),
])
def test_parse_param(text, expected):
    assert parse_param(text) == expected


@pytest.mark.parametrize("text", ["steps", "=3", " =3"])
def test_parse_param_needs_key_and_equals(text):
    with pytest.raises(argparse.ArgumentTypeError, match="KEY=VALUE"):
        parse_param(text)


def test_collect_params_merges_the_file_and_repeats(tmp_path):
    file = tmp_path / "params.json"
    file.write_text(json.dumps({"dataset": "demo", "steps": 10, "methods": ["svgf"]}))
    params = collect_params(file, [("steps", 20), ("methods", "svgf"), ("methods", "oidn:high")])
    assert params == {"dataset": "demo", "steps": 20, "methods": ["svgf", "oidn:high"]}


@pytest.mark.parametrize("content, message", [
    (None, "No such file"), ("{not json", "not valid JSON"), ("[1, 2]", "expected a JSON object"),
])
def test_bad_params_json_exits_2(api, tmp_path, capsys, content, message):
    file = tmp_path / "params.json"
    if content is not None:
        file.write_text(content)
    assert main(["submit", "train", "--params-json", str(file)]) == 2
    assert message in capsys.readouterr().err
    assert api.jobs == {}


def test_bad_param_is_an_argparse_error(capsys):
    with pytest.raises(SystemExit) as info:
        main(["submit", "train", "--param", "steps"])
    assert info.value.code == 2
    assert "expected KEY=VALUE, got 'steps'" in capsys.readouterr().err


def test_params_json_from_stdin(api, monkeypatch):
    monkeypatch.setattr(sys, "stdin", io.StringIO('{"steps": 3}'))
    assert main(["submit", "train", "--params-json", "-", "--param", "method=wskpn:xs", "--device", "gpu"]) == 0
    job = next(iter(api.jobs.values()))
    assert job["params"] == {"steps": 3, "method": "wskpn:xs"} and job["queue"] == "gpu"


# --- jobs ----------------------------------------------------------------------------------------------------


def test_submit_follow_prints_progress_lines_and_the_result(api, capsys):
    assert main(["submit", "evaluate", "--param", "methods=svgf", "--follow", "--progress", "lines",
                 "--poll", "0"]) == 0
    out, err = capsys.readouterr()
    assert "submitted evaluate job job-0001 (queue cpu, state queued)" in out
    assert err.splitlines() == ["[queued] 0/4 (0%)  waiting for a worker",
                                "[running] 1/4 (25%)  step 1  eta 3s",
                                "[running] 3/4 (75%)  step 3  eta 1s",
                                "[succeeded] 4/4 (100%)  done"]
    assert "job job-0001 succeeded" in out and '"psnr": 31.5' in out
    assert "mlflow run: http://mlflow.test/#/runs/run-1" in out


def test_submit_follow_with_a_bar(api, capsys):
    assert main(["submit", "train", "--follow", "--progress", "bar", "--poll", "0"]) == 0
    out, err = capsys.readouterr()
    assert "4/4" in err and "succeeded" in err  # tqdm draws on stderr
    assert "job job-0001 succeeded" in out


def test_follow_of_a_failed_job_exits_1(api, capsys):
    api.script = [("running", {"current": 1, "total": 2}), ("failed", {"current": 1, "total": 2})]
    api.final_error = {"code": "worker_error", "message": "CUDA out of memory"}
    assert main(["submit", "train", "--follow", "--progress", "none", "--poll", "0"]) == 1
    out = capsys.readouterr().out
    assert "job job-0001 failed" in out and "error (worker_error): CUDA out of memory" in out


def test_job_shows_logs_and_cancels(api, capsys):
    main(["submit", "train", "--param", "steps=5"])
    capsys.readouterr()
    assert main(["job", "job-0001", "--logs", "2"]) == 0
    out = capsys.readouterr().out
    assert "job job-0001: train on cpu" in out and '"steps": 5' in out
    assert out.rstrip().endswith("line 8\nline 9")
    assert main(["job", "job-0001", "--cancel"]) == 0
    assert "asked job job-0001 to cancel" in capsys.readouterr().out
    assert main(["job", "job-0001", "--cancel"]) == 2  # already finished: the server's 409
    assert "409 conflict" in capsys.readouterr().err


def test_jobs_table_filters(api, capsys):
    main(["submit", "train"])
    main(["submit", "evaluate"])
    capsys.readouterr()
    assert main(["jobs", "--kind", "evaluate"]) == 0
    lines = capsys.readouterr().out.splitlines()
    assert lines[0].split() == ["id", "kind", "state", "queue", "progress", "created"]
    assert len(lines) == 2 and "job-0002" in lines[1] and "evaluate" in lines[1]
    assert main(["jobs", "--state", "running"]) == 0
    assert capsys.readouterr().out.strip() == "no jobs"


def test_results_download(api, tmp_path, capsys):
    buffer = io.BytesIO()
    with zipfile.ZipFile(buffer, "w") as zipped:
        zipped.writestr("seq_a/frame_0000.exr", b"exr")
    api.results_zip = buffer.getvalue()
    main(["submit", "infer"])
    assert main(["results", "job-0001", "--out", str(tmp_path / "out")]) == 0
    assert "wrote 1 file(s)" in capsys.readouterr().out
    assert (tmp_path / "out" / "seq_a" / "frame_0000.exr").read_bytes() == b"exr"


# --- datasets, models ----------------------------------------------------------------------------------------


def test_upload_and_datasets(api, tmp_path, capsys):
    write_frame_sequence(tmp_path / "loose", "seq_a", 2)
    (tmp_path / "loose" / "notes.txt").write_text("x")
    assert main(["upload", str(tmp_path / "loose"), "--name", "demo", "--split", "test"]) == 0
    out, err = capsys.readouterr()
    assert "uploaded dataset demo: 1 sequences, 2 frames" in out
    assert "left out 1 file(s) no manifest lists: notes.txt" in err
    assert api.uploads[-1][0] == {"split": "test", "name": "demo"}
    assert main(["upload", str(tmp_path / "missing")]) == 2
    assert main(["datasets"]) == 0
    assert "demo" in capsys.readouterr().out
    assert main(["datasets", "demo"]) == 0
    assert "seq_a" in capsys.readouterr().out
    assert main(["datasets", "demo", "--delete"]) == 0
    assert main(["datasets", "demo"]) == 2


def test_models_and_alias(api, capsys):
    assert main(["models"]) == 0
    out = capsys.readouterr().out
    assert "wskpn-xs" in out and "champion->1" in out
    assert main(["models", "wskpn-xs"]) == 0
    lines = capsys.readouterr().out.splitlines()
    assert lines[1].split() == ["version", "method", "scale", "val", "PSNR", "ms/frame", "aliases", "created"]
    assert lines[2].split()[:6] == ["1", "wskpn:xs", "1", "30.25", "4.50", "champion"]
    assert main(["alias", "wskpn-xs", "champion", "2"]) == 0
    assert "wskpn-xs@champion -> version 2" in capsys.readouterr().out
    assert api.models["wskpn-xs"]["aliases"] == {"champion": "2"}
    assert main(["models", "nope"]) == 2


# --- stream --------------------------------------------------------------------------------------------------


def test_stream_prints_timings_and_writes_exrs(api, tmp_path, capsys):
    sequence = write_frame_sequence(tmp_path / "data", "seq_a", 3)
    assert main(["stream", str(sequence), "--model", "wskpn-xs", "--alias", "champion", "--out",
                 str(tmp_path / "out"), "--transport", "http"]) == 0
    out = capsys.readouterr().out.splitlines()
    assert out[0].startswith("session s1: wskpn-xs version 1 (wskpn:xs, scale 1), 3 frames")
    assert [line.split()[1] for line in out[1:4]] == ["0", "1", "2"]
    assert "inference    1.50 ms" in out[1] and "started" in out[1] and "continued" in out[2]
    assert out[4].startswith("3 frames in") and "median inference    1.50 ms" in out[4]
    assert "history: started 1, continued 2" in out[4]
    assert sorted(p.name for p in (tmp_path / "out").iterdir()) == [f"frame_000{i}.exr" for i in range(3)]
    assert api.sessions == {}  # deleted at the end


def test_stream_takes_a_plain_folder_of_a_renderers_frames_with_its_layout(api, tmp_path, capsys):
    from tests.model.layouts.exr_builders import BLENDER_ORBIT

    assert main(["stream", str(BLENDER_ORBIT), "--layout", "blender-cycles", "--model", "wskpn-xs", "--out",
                 str(tmp_path / "out"), "--transport", "http"]) == 0
    out = capsys.readouterr().out.splitlines()
    assert out[0].endswith(", 4 frames")
    assert [line.split()[1] for line in out[1:5]] == ["1", "2", "3", "4"]  # Blender's frame numbers
    assert "continued" in out[4]
    assert len(list((tmp_path / "out").glob("frame_*.exr"))) == 4
    # A layout file goes to the server as the layout itself; the session reads the frames in it.
    layout = tmp_path / "cycles.json"
    from model.layouts.builtin import BLENDER_CYCLES

    layout.write_text(json.dumps(dict(BLENDER_CYCLES, name="mine")))
    assert main(["stream", str(BLENDER_ORBIT), "--layout", str(layout), "--model", "wskpn-xs", "--out",
                 str(tmp_path / "out2"), "--keep-session", "--transport", "http"]) == 0
    assert next(iter(api.sessions.values())).layout["name"] == "mine"
    assert main(["stream", str(BLENDER_ORBIT), "--layout", "arnold", "--model", "wskpn-xs", "--out",
                 str(tmp_path / "out3")]) == 2
    assert "not a built-in layout" in capsys.readouterr().err


def test_stream_reads_a_renderers_folder_beside_its_own_manifest_and_writes_pngs(api, tmp_path, capsys):
    from tests.model.layouts.exr_builders import BLENDER_ORBIT

    folder = tmp_path / "orbit"
    shutil.copytree(BLENDER_ORBIT, folder)
    (folder / "manifest.json").write_text(json.dumps({"format": None, "renderer": "cycles"}))
    assert main(["stream", str(folder), "--layout", "blender-cycles", "--model", "wskpn-xs", "--out",
                 str(tmp_path / "out"), "--transport", "http", "--png", "--quiet"]) == 0
    captured = capsys.readouterr()
    assert "ignored 2 file(s) that are not frames: cameras.json, manifest.json" in captured.err
    assert "wrote 4 EXR(s) and 4 PNG(s)" in captured.out
    names = sorted(p.name for p in (tmp_path / "out").iterdir())
    assert names == [f"frame_000{i}.{suffix}" for i in range(4) for suffix in ("exr", "png")]
    # A frame bundle sequence (this project's manifest) gets its PNGs too: the display encoding of each output.
    sequence = write_frame_sequence(tmp_path / "data", "seq_a", 2)
    assert main(["stream", str(sequence), "--model", "wskpn-xs", "--out", str(tmp_path / "b"), "--transport", "http",
                 "--png", "--quiet"]) == 0
    from client.frames import decode_image_exr, display_encode, encode_png

    output = decode_image_exr((tmp_path / "b" / "frame_0001.exr").read_bytes())
    assert (tmp_path / "b" / "frame_0001.png").read_bytes() == encode_png(output)
    assert display_encode(output).max() > 0


def test_upload_leaves_a_renderers_own_manifest_out(api, tmp_path, capsys):
    root = tmp_path / "export"
    write_frame_sequence(root, "seq_a", 2)
    (root / "manifest.json").write_text(json.dumps({"pipeline": "nuke", "shots": ["seq_a"]}))
    assert main(["upload", str(root), "--name", "mixed"]) == 0
    assert sorted(api.uploads[-1][3]) == ["export/seq_a/frame_0000.exr", "export/seq_a/frame_0001.exr",
                                          "export/seq_a/manifest.json"]
    assert "left out 1 file(s) no manifest lists: manifest.json" in capsys.readouterr().err


def test_upload_with_a_layout_sends_the_render_folder_or_converts_it_with_a_layout_file(api, tmp_path, capsys):
    from tests.model.layouts.exr_builders import BLENDER_ORBIT

    assert main(["upload", str(BLENDER_ORBIT), "--name", "blender", "--layout", "blender-cycles"]) == 0
    params, _, _, members = api.uploads[-1]
    assert params["layout"] == "blender-cycles"
    assert "blender_orbit/frame_0000.exr" in members and "blender_orbit/references/frame_0003.exr" in members
    assert "left out 1 file(s)" in capsys.readouterr().err  # cameras.json
    layout = tmp_path / "cycles.json"
    from model.layouts.builtin import BLENDER_CYCLES

    layout.write_text(json.dumps(dict(BLENDER_CYCLES, name="mine")))
    assert main(["upload", str(BLENDER_ORBIT), "--name", "converted", "--layout", str(layout)]) == 0
    params, _, _, members = api.uploads[-1]
    assert "layout" not in params  # converted here into our format: a dataset folder with manifests
    assert "dataset/manifest.json" in members and "dataset/blender_orbit/manifest.json" in members


def test_stream_errors(api, tmp_path, capsys):
    # A folder without manifest.json is a renderer's plain folder of EXRs; one without any is refused.
    assert main(["stream", str(tmp_path), "--model", "wskpn-xs", "--out", str(tmp_path / "out")]) == 2
    assert "holds no .exr files" in capsys.readouterr().err
    sequence = write_frame_sequence(tmp_path / "data", "seq_a", 2)
    assert main(["stream", str(sequence), "--model", "nope", "--out", str(tmp_path / "out")]) == 2
    assert "registered model 'nope' does not exist" in capsys.readouterr().err
    with pytest.raises(SystemExit):
        main(["stream", str(sequence), "--model", "m", "--version", "1", "--alias", "a", "--out", "x"])


# --- serve, worker, mlflow-ui --------------------------------------------------------------------------------


def test_serve_runs_uvicorn_on_the_app(monkeypatch):
    import uvicorn

    from core.settings import get_settings

    calls = []
    monkeypatch.setattr(uvicorn, "run", lambda target, **options: calls.append((target, options)))
    monkeypatch.setenv("DENOISER_API_KEY", "0123456789abcdef0123")  # every interface: a real key is required
    get_settings.cache_clear()
    try:
        assert main(["serve", "--host", "0.0.0.0", "--port", "8080"]) == 0
        assert calls == [("service.http.app:app", {"host": "0.0.0.0", "port": 8080, "log_level": "info",
                                           "reload": False, "ws_max_size": 256 * 1024**2})]
        with pytest.raises(SystemExit):
            main(["serve", "--port", "70000"])
    finally:
        get_settings.cache_clear()  # the key set here must not outlive the test


def test_worker_runs_the_celery_app_with_the_solo_pool(monkeypatch, capsys):
    calls = []
    monkeypatch.setattr(serve_commands.os, "execv", lambda path, argv: calls.append(argv) if path == argv[0] else None)
    assert main(["worker", "--queues", "cpu,gpu", "--loglevel", "debug"]) == 0
    assert calls == [[sys.executable, "-m", "celery", "-A", "core.celery_app",
                      "worker", "--pool=solo", "--queues=cpu,gpu", "--loglevel=DEBUG"]]
    assert main(["worker", "--queues", "cpu,tpu"]) == 2
    assert "unknown: tpu" in capsys.readouterr().err
    with pytest.raises(UsageError):
        serve_commands.worker_argv(" , ", "info")


def test_mlflow_ui_runs_on_the_resolved_tracking_uri(monkeypatch, tmp_path, capsys):
    from core.settings import get_settings

    calls = []
    monkeypatch.setattr(serve_commands.subprocess, "call", lambda argv: calls.append(argv) or 0)
    monkeypatch.setenv("DENOISER_DATA_DIR", str(tmp_path / "var"))
    monkeypatch.delenv("DENOISER_TRACKING_URI", raising=False)
    get_settings.cache_clear()
    try:
        assert main(["mlflow-ui", "--port", "5055"]) == 0
    finally:
        get_settings.cache_clear()
    database = (tmp_path / "var" / "mlflow" / "mlflow.db").resolve()
    assert calls == [[sys.executable, "-m", "mlflow", "ui", "--backend-store-uri", f"sqlite:///{database}",
                      "--host", "127.0.0.1", "--port", "5055"]]
    assert database.parent.is_dir()
    assert main(["mlflow-ui", "--tracking-uri", "http://mlflow:5000"]) == 2
    assert "open it in a browser" in capsys.readouterr().err


def test_models_delete_a_version_or_a_model(api, capsys):
    assert main(["models", "wskpn-xs", "--delete", "--version", "1"]) == 0
    assert "deleted wskpn-xs version 1" in capsys.readouterr().out
    assert "1" not in {v["version"] for v in api.models["wskpn-xs"]["versions"]}
    assert main(["models", "wskpn-xs", "--delete", "--version", "1"]) == 2
    assert "version 1 of model 'wskpn-xs' does not exist" in capsys.readouterr().err
    assert main(["models", "wskpn-xs", "--delete"]) == 0 and "wskpn-xs" not in api.models
    assert main(["models", "--delete"]) == 2  # which model?
    assert "--delete needs a model NAME" in capsys.readouterr().err
