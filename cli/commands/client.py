"""Subcommands that talk to a running denoiser service over HTTP (client.rest.DenoiserClient).

`upload`, `datasets`, `submit`, `job`, `jobs`, `results`, `models`, `alias`, `stream`. Each takes `--url`
and `--api-key` (defaults: the settings ``url`` and ``api_key``, DENOISER_URL and DENOISER_API_KEY). A server that
cannot be reached and a 4xx answer exit with status 2 and one line naming the URL or quoting the server's
message; a 5xx exits with 1.
"""

from __future__ import annotations

import argparse
import functools
import json
import sys
import tempfile
from pathlib import Path

from cli.main import EXIT_FAILURE, UsageError, positive_int
from core.names import DEVICES, JOB_KINDS, JOB_STATES, SPLITS
from core.settings import Settings, get_settings

DEFAULT_URL = Settings.model_fields["url"].default


def add_commands(commands) -> None:
    common = argparse.ArgumentParser(add_help=False)
    server = common.add_argument_group("server")
    server.add_argument("--url", default=None, metavar="URL",
                        help=f"service address (default: $DENOISER_URL or {DEFAULT_URL})")
    server.add_argument("--api-key", default=None, metavar="KEY",
                        help="X-API-Key to send (default: $DENOISER_API_KEY)")
    server.add_argument("--timeout", type=float, default=60.0, metavar="SECONDS",
                        help="limit on each network operation (connect, each read or write)")
    _add_upload(commands, common)
    _add_datasets(commands, common)
    _add_submit(commands, common)
    _add_job(commands, common)
    _add_jobs(commands, common)
    _add_results(commands, common)
    _add_models(commands, common)
    _add_alias(commands, common)
    _add_stream(commands, common)


def _client(args):
    from client.rest import DenoiserClient

    settings = get_settings()  # DENOISER_URL and DENOISER_API_KEY, read with every other setting
    api_key = args.api_key if args.api_key is not None else settings.api_key
    return DenoiserClient(args.url or settings.url, api_key=api_key or None, timeout=args.timeout)


def _talks_to_server(run):
    """Map the client's errors onto the CLI's exit statuses: unreachable or 4xx -> 2 (UsageError), 5xx -> 1."""

    @functools.wraps(run)
    def wrapper(args) -> int:
        from client.rest import ApiClientError, ServerUnreachable

        try:
            return run(args)
        except ServerUnreachable as error:
            raise UsageError(f"{error}; start it with 'denoiser serve' or pass --url / set DENOISER_URL") from None
        except ApiClientError as error:
            if error.is_client_error:
                raise UsageError(f"the server refused the request ({error.status} {error.code}): "
                                 f"{error.message}") from None
            print(f"denoiser {args.command}: server error ({error.status} {error.code}): {error.message}",
                  file=sys.stderr)
            return EXIT_FAILURE

    return wrapper


def _print_json(value) -> None:
    """The client's typed answers print as the JSON the server sent (to_dict)."""
    print(json.dumps(value, indent=2, default=lambda item: item.to_dict() if hasattr(item, "to_dict") else str(item)))


# --------------------------------------------------------------------------------------------- datasets

def _add_upload(commands, common) -> None:
    parser = commands.add_parser(
        "upload", parents=[common], help="upload a dataset folder, sequence folder(s) or a zip/tar to the service",
        description="Upload SOURCE as a new dataset. A folder (a dataset with manifest.json and splits, one "
                    "sequence folder, or a folder of sequence folders) is packed into a temporary tar holding "
                    "only the manifests and the frames they list, then streamed; a .zip, .tar or .tar.gz is "
                    "sent as it is. The server validates every frame before the dataset appears.")
    parser.add_argument("source", type=Path, metavar="DIR|ARCHIVE", help="folder or archive to upload")
    parser.add_argument("--name", default=None, help="dataset id to ask for (409 if taken); default: server-made")
    parser.add_argument("--split", choices=SPLITS, default="train",
                        help="split of sequences the upload gives none (a dataset manifest's splits win)")
    parser.add_argument("--layout", default=None, metavar="NAME|FILE",
                        help="the frames' layout: a built-in one other than denoiser (blender-cycles, generic) sends "
                             "a renderer's sequence folder (frame EXRs + references/) or a folder of them for the "
                             "server to convert; a layout file converts them here first (as denoiser import)")
    parser.add_argument("--json", action="store_true", help="print the dataset record as JSON")
    parser.set_defaults(run=_talks_to_server(_run_upload))


def _run_upload(args) -> int:
    if not args.source.exists():
        raise UsageError(f"{args.source}: no such folder or archive")
    skipped: list[str] = []
    with tempfile.TemporaryDirectory(prefix="denoiser-import-") as work, _client(args) as client:
        source, layout = _converted_for_upload(args.source, args.layout, Path(work), args.split)
        dataset = client.upload_dataset(source, name=args.name, split=args.split, skipped=skipped, layout=layout)
    if skipped:
        shown = ", ".join(skipped[:5]) + (f" and {len(skipped) - 5} more" if len(skipped) > 5 else "")
        print(f"left out {len(skipped)} file(s) no manifest lists: {shown}", file=sys.stderr)
    if args.json:
        _print_json(dataset)
    else:
        print(f"uploaded dataset {dataset.get('id')}: {_dataset_line(dataset)}")
    return 0


def _converted_for_upload(source: Path, layout: str | None, work: Path, split: str) -> tuple[Path, str | None]:
    """(what to upload, the layout to name to the server): a layout file is applied here (the server knows only
    the built-in layouts), turning the renderer's folder(s) into a dataset folder in ``work``."""
    from model.layouts import BUILTIN_LAYOUTS, LayoutError, load_layout

    if layout is None or layout in BUILTIN_LAYOUTS:
        return source, layout
    try:
        chosen = load_layout(layout)
    except LayoutError as error:
        raise UsageError(str(error)) from None
    from model.io.importer import frame_files, import_sequence

    if not source.is_dir():
        raise UsageError(f"{source}: --layout FILE converts a folder of frame EXRs, not an archive")
    has_frames = any(path.suffix.lower() == ".exr" for path in source.iterdir())
    folders = [source] if has_frames else [entry for entry in sorted(source.iterdir()) if entry.is_dir()]
    for folder in folders:
        frame_files(folder)  # a folder without frames: a clear error before anything is converted
        report = import_sequence(folder, chosen, work / "dataset", split=split)
        for warning in report.warnings:
            print(f"warning: {folder.name}: {warning}", file=sys.stderr)
    return work / "dataset", None


def _dataset_line(dataset: dict) -> str:
    sequences = dataset.get("sequences")
    count = len(sequences) if isinstance(sequences, list) else sequences
    splits = dataset.get("splits") or {}
    per_split = ", ".join(f"{split} {value.get('sequences', value) if isinstance(value, dict) else value}"
                          for split, value in splits.items())
    scenes = ", ".join(dataset.get("scenes") or []) or "-"
    return f"{count} sequences, {dataset.get('frames')} frames ({per_split}); scenes: {scenes}"


def _add_datasets(commands, common) -> None:
    parser = commands.add_parser("datasets", parents=[common], help="list the service's datasets, show or delete one")
    parser.add_argument("dataset", nargs="?", default=None, metavar="ID", help="show this dataset's sequences")
    parser.add_argument("--delete", action="store_true", help="delete dataset ID")
    parser.add_argument("--json", action="store_true", help="print JSON instead of a table")
    parser.set_defaults(run=_talks_to_server(_run_datasets))


def _run_datasets(args) -> int:
    if args.delete and args.dataset is None:
        raise UsageError("--delete needs a dataset ID")
    with _client(args) as client:
        if args.delete:
            client.delete_dataset(args.dataset)
            print(f"deleted dataset {args.dataset}")
            return 0
        if args.dataset is not None:
            dataset = client.get_dataset(args.dataset)
            if args.json:
                _print_json(dataset)
                return 0
            print(f"{dataset.get('id')}: {_dataset_line(dataset)}")
            rows = [(s.get("name"), s.get("split"), s.get("scene") or "-", str(s.get("frames")),
                     f"{s.get('width')}x{s.get('height')}", ",".join(map(str, s.get("scales") or [])) or "-")
                    for s in dataset.get("sequences") or []]
            _print_table(("sequence", "split", "scene", "frames", "size", "scales"), rows)
            return 0
        datasets = client.list_datasets()
    if args.json:
        _print_json(datasets)
        return 0
    rows = [(d.get("id"), str(d.get("sequences")), str(d.get("frames")),
             " ".join(f"{k}:{v}" for k, v in (d.get("splits") or {}).items()), ", ".join(d.get("scenes") or []))
            for d in datasets]
    _print_table(("id", "sequences", "frames", "splits", "scenes"), rows, empty="no datasets")
    return 0


# ------------------------------------------------------------------------------------------------- jobs

def parse_param(text: str) -> tuple[str, object]:
    """'key=value' -> (key, value); the value is JSON when it parses as JSON (8, 1e-3, true, ["a"]), else text."""
    key, separator, value = text.partition("=")
    key = key.strip()
    if not separator or not key:
        raise argparse.ArgumentTypeError(f"expected KEY=VALUE, got {text!r}")
    try:
        return key, json.loads(value)
    except ValueError:
        return key, value


def collect_params(params_json: Path | None, pairs: list[tuple[str, object]]) -> dict:
    """--params-json FILE ('-' for stdin) first, then each --param on top; a key given twice becomes a list."""
    params: dict = {}
    if params_json is not None:
        try:
            text = sys.stdin.read() if str(params_json) == "-" else params_json.read_text()
        except OSError as error:
            raise UsageError(f"--params-json {params_json}: {error.strerror or error}") from None
        try:
            params = json.loads(text)
        except ValueError as error:
            raise UsageError(f"--params-json {params_json}: not valid JSON ({error})") from None
        if not isinstance(params, dict):
            raise UsageError(f"--params-json {params_json}: expected a JSON object, got {type(params).__name__}")
    repeated: dict[str, list] = {}
    for key, value in pairs:
        repeated.setdefault(key, []).append(value)
    for key, values in repeated.items():
        params[key] = values[0] if len(values) == 1 else values
    return params


def _add_submit(commands, common) -> None:
    parser = commands.add_parser(
        "submit", parents=[common], help="queue a job (generate, train, evaluate, benchmark, infer, fit)",
        description="POST /jobs. Parameters come from --params-json and then each --param KEY=VALUE; a VALUE is "
                    "read as JSON when it is valid JSON (8, 0.001, true, [\"a\",\"b\"], null) and as text "
                    "otherwise; a KEY given twice collects its values into a list "
                    "(--param methods=svgf --param methods=oidn:high). With --follow, progress is shown until "
                    "the job ends and the exit status is 0 only if it succeeded.",
        epilog="example: denoiser submit train --param dataset=demo --param method=wskpn:xs --param steps=200 "
               "--follow")
    parser.add_argument("kind", choices=JOB_KINDS, help="job kind")
    parser.add_argument("--param", type=parse_param, action="append", default=[], metavar="KEY=VALUE",
                        help="one job parameter; repeat for several")
    parser.add_argument("--params-json", type=Path, default=None, metavar="FILE",
                        help="JSON object of parameters ('-' reads stdin); --param values override it")
    parser.add_argument("--device", choices=DEVICES, default="cpu", help="queue (and device) to run on")
    _add_follow_options(parser)
    parser.set_defaults(run=_talks_to_server(_run_submit))


def _add_follow_options(parser) -> None:
    parser.add_argument("--follow", action="store_true", help="wait for the job, showing progress, then its result")
    parser.add_argument("--progress", choices=("auto", "bar", "lines", "none"), default="auto",
                        help="how --follow shows progress: a tqdm bar, one line per change, or nothing; "
                             "auto: a bar on a terminal, lines otherwise")
    parser.add_argument("--poll", type=float, default=0.5, metavar="SECONDS",
                        help="first interval between polls (grows to 5 s while nothing changes)")


def _run_submit(args) -> int:
    params = collect_params(args.params_json, args.param)
    with _client(args) as client:
        job = client.submit_job(args.kind, params, device=args.device)
        print(f"submitted {job.get('kind', args.kind)} job {job.get('id')} (queue {job.get('queue', args.device)}, "
              f"state {job.get('state')})")
        if not args.follow:
            return 0
        return _follow(client, job["id"], args)


def _follow(client, job_id: str, args) -> int:
    mode = args.progress
    if mode == "auto":
        mode = "bar" if sys.stderr.isatty() else "lines"
    reporter = _BarReporter() if mode == "bar" else _LineReporter() if mode == "lines" else None
    try:
        job = client.wait_job(job_id, reporter, interval=args.poll)
    except KeyboardInterrupt:
        print(f"\nstopped following; job {job_id} goes on (denoiser job {job_id} --follow, or --cancel)",
              file=sys.stderr)
        raise
    finally:
        if reporter is not None:
            reporter.close()
    _print_final(job)
    return 0 if job.get("state") == "succeeded" else EXIT_FAILURE


class _LineReporter:
    """One line on stderr per change of state or progress."""

    def __call__(self, job: dict) -> None:
        print(f"[{job.get('state')}] {_progress_text(job)}", file=sys.stderr, flush=True)

    def close(self) -> None:
        pass


class _BarReporter:
    """A tqdm bar over progress.current / progress.total, its description the state and message."""

    def __init__(self) -> None:
        self._bar = None

    def __call__(self, job: dict) -> None:
        from tqdm import tqdm

        progress = job.get("progress") or {}
        total, current = progress.get("total"), progress.get("current")
        if self._bar is None:
            self._bar = tqdm(total=total, unit="step", file=sys.stderr, dynamic_ncols=True)
        if total is not None and self._bar.total != total:
            self._bar.total = total
        if current is not None:
            self._bar.n = current
        self._bar.set_description_str(f"{job.get('state')}")
        self._bar.set_postfix_str(progress.get("message") or "", refresh=False)
        self._bar.refresh()

    def close(self) -> None:
        if self._bar is not None:
            self._bar.close()


def _progress_text(job: dict) -> str:
    progress = job.get("progress") or {}
    parts = []
    if progress.get("total"):
        current = progress.get("current") or 0
        parts.append(f"{current}/{progress['total']} ({100.0 * current / progress['total']:.0f}%)")
    elif progress.get("current") is not None:
        parts.append(str(progress["current"]))
    if progress.get("message"):
        parts.append(str(progress["message"]))
    if progress.get("eta_seconds") is not None and job.get("state") == "running":
        parts.append(f"eta {_duration(progress['eta_seconds'])}")
    return "  ".join(parts) or "-"


def _duration(seconds: float) -> str:
    seconds = int(round(float(seconds)))
    return f"{seconds // 3600}h{seconds % 3600 // 60:02d}m" if seconds >= 3600 else \
        f"{seconds // 60}m{seconds % 60:02d}s" if seconds >= 60 else f"{seconds}s"


def _print_final(job: dict) -> None:
    print(f"job {job.get('id')} {job.get('state')}")
    if job.get("mlflow_url") or job.get("mlflow_run_id"):
        print(f"mlflow run: {job.get('mlflow_url') or job.get('mlflow_run_id')}")
    if job.get("error"):
        error = job["error"]
        print(f"error ({error.get('code')}): {error.get('message')}" if isinstance(error, dict) else f"error: {error}")
    if job.get("result") is not None:
        print("result:")
        _print_json(job["result"])


def _print_job(job: dict) -> None:
    print(f"job {job.get('id')}: {job.get('kind')} on {job.get('queue') or job.get('device')}, {job.get('state')}")
    print(f"  progress: {_progress_text(job)}")
    for key in ("created_at", "started_at", "finished_at", "attempts"):
        if job.get(key) is not None:
            print(f"  {key.replace('_', ' ')}: {job[key]}")
    print(f"  params: {json.dumps(job.get('params') or {}, sort_keys=True)}")
    if job.get("mlflow_url") or job.get("mlflow_run_id"):
        print(f"  mlflow run: {job.get('mlflow_url') or job.get('mlflow_run_id')}")
    if job.get("error"):
        error = job["error"]
        print(f"  error ({error.get('code')}): {error.get('message')}" if isinstance(error, dict)
              else f"  error: {error}")
    if job.get("result") is not None:
        print(f"  result: {json.dumps(job['result'], sort_keys=True, default=str)}")


def _add_job(commands, common) -> None:
    parser = commands.add_parser("job", parents=[common], help="show one job; follow it, print its logs, or cancel it")
    parser.add_argument("job_id", metavar="ID", help="job id (as 'denoiser submit' printed it)")
    parser.add_argument("--logs", type=positive_int, default=None, metavar="N", help="print the job's last N log lines")
    parser.add_argument("--cancel", action="store_true",
                        help="ask the job to stop (cooperative: it ends at its next check)")
    parser.add_argument("--json", action="store_true", help="print the job record as JSON")
    _add_follow_options(parser)
    parser.set_defaults(run=_talks_to_server(_run_job))


def _run_job(args) -> int:
    with _client(args) as client:
        if args.cancel:
            client.cancel_job(args.job_id)
            print(f"asked job {args.job_id} to cancel")
        if args.follow:
            status = _follow(client, args.job_id, args)
        else:
            job = client.get_job(args.job_id)
            _print_json(job) if args.json else _print_job(job)
            status = 0
        if args.logs is not None:
            lines = client.job_logs(args.job_id, lines=args.logs)
            print(f"--- last {len(lines)} log line(s) of job {args.job_id} ---")
            for line in lines:
                print(line)
    return status


def _add_jobs(commands, common) -> None:
    parser = commands.add_parser("jobs", parents=[common], help="list jobs, newest first")
    parser.add_argument("--kind", choices=JOB_KINDS, default=None, help="only jobs of this kind")
    parser.add_argument("--state", choices=JOB_STATES, default=None, help="only jobs in this state")
    parser.add_argument("--limit", type=positive_int, default=50, help="at most this many")
    parser.add_argument("--json", action="store_true", help="print JSON instead of a table")
    parser.set_defaults(run=_talks_to_server(_run_jobs))


def _run_jobs(args) -> int:
    with _client(args) as client:
        jobs = client.list_jobs(kind=args.kind, state=args.state, limit=args.limit)
    if args.json:
        _print_json(jobs)
        return 0
    rows = [(j.get("id"), j.get("kind"), j.get("state"), j.get("queue") or j.get("device") or "-",
             _progress_text(j), str(j.get("created_at") or "-")) for j in jobs]
    _print_table(("id", "kind", "state", "queue", "progress", "created"), rows, empty="no jobs")
    return 0


def _add_results(commands, common) -> None:
    parser = commands.add_parser("results", parents=[common], help="download an infer job's output EXRs")
    parser.add_argument("job_id", metavar="JOB_ID", help="a succeeded infer job")
    parser.add_argument("--out", type=Path, required=True, metavar="DIR", help="folder to extract results.zip into")
    parser.add_argument("--zip", action="store_true", help="keep results.zip instead of extracting it")
    parser.set_defaults(run=_talks_to_server(_run_results))


def _run_results(args) -> int:
    if args.out.exists() and not args.out.is_dir():
        raise UsageError(f"--out {args.out} is a file; give a folder")
    with _client(args) as client:
        files = client.download_results(args.job_id, args.out, extract=not args.zip)
    print(f"wrote {len(files)} file(s) under {args.out}")
    return 0


# ----------------------------------------------------------------------------------------------- models

def _add_models(commands, common) -> None:
    parser = commands.add_parser("models", parents=[common],
                                 help="list registered models, show one model's versions with tags and metrics, "
                                      "or delete a model or version")
    parser.add_argument("name", nargs="?", default=None, metavar="NAME", help="show this model's versions")
    parser.add_argument("--json", action="store_true", help="print JSON instead of a table")
    parser.add_argument("--delete", action="store_true",
                        help="delete model NAME (with --version V: only that version) instead of showing it")
    parser.add_argument("--version", default=None, metavar="V", help="with --delete: the version to delete")
    parser.set_defaults(run=_talks_to_server(_run_models))


def _run_models(args) -> int:
    if args.delete or args.version is not None:
        if not (args.delete and args.name):
            raise UsageError("--delete needs a model NAME (and --version V to delete one version only); "
                             "--version is only for --delete")
        with _client(args) as client:
            if args.version is None:
                client.delete_model(args.name)
            else:
                client.delete_model_version(args.name, args.version)
        print(f"deleted {args.name}" + (f" version {args.version}" if args.version is not None else ""))
        return 0
    with _client(args) as client:
        body = client.get_model(args.name) if args.name else client.list_models()
    if args.json:
        _print_json(body)
        return 0
    if args.name is None:
        rows = [(m.get("name"), str(m.get("latest_version") or "-"),
                 " ".join(f"{a}->{v}" for a, v in (m.get("aliases") or {}).items()) or "-",
                 m.get("description") or "") for m in body]
        _print_table(("model", "latest", "aliases", "description"), rows, empty="no registered models")
        return 0
    aliases = body.get("aliases") or {}
    print(f"{body.get('name')}: {body.get('description') or ''}".rstrip(": "))
    by_version: dict[str, list[str]] = {}
    for alias, version in aliases.items():
        by_version.setdefault(str(version), []).append(alias)
    rows = []
    for version in body.get("versions") or []:
        tags = version.get("tags") or {}
        metrics = version.get("metrics") or {}
        method = tags.get("method", version.get("method", "-"))
        preset = tags.get("preset", version.get("preset"))
        rows.append((str(version.get("version")), f"{method}:{preset}" if preset else str(method),
                     str(tags.get("scale", version.get("scale", "-"))),
                     _number(metrics.get("validation_psnr")), _number(metrics.get("ms_per_frame")),
                     ",".join(by_version.get(str(version.get("version")), [])) or "-",
                     str(version.get("created_at") or "-")))
    _print_table(("version", "method", "scale", "val PSNR", "ms/frame", "aliases", "created"), rows,
                 empty="no versions")
    return 0


def _number(value) -> str:
    return "-" if value is None else f"{float(value):.2f}" if isinstance(value, (int, float)) else str(value)


def _add_alias(commands, common) -> None:
    parser = commands.add_parser("alias", parents=[common], help="point a model alias (e.g. champion) at a version")
    parser.add_argument("name", metavar="NAME", help="registered model")
    parser.add_argument("alias", metavar="ALIAS", help="alias to set, e.g. champion")
    parser.add_argument("version", metavar="VERSION", help="model version the alias should point at")
    parser.set_defaults(run=_talks_to_server(_run_alias))


def _run_alias(args) -> int:
    with _client(args) as client:
        client.set_alias(args.name, args.alias, args.version)
    print(f"{args.name}@{args.alias} -> version {args.version}")
    return 0


# ----------------------------------------------------------------------------------------------- stream

def _add_stream(commands, common) -> None:
    parser = commands.add_parser(
        "stream", parents=[common], help="denoise a sequence folder frame by frame through a model session",
        description="Open a session on a registered model, a pretrained model or a method without weights (as "
                    "'denoiser evaluate' names them: oidn:high, svgf), send every frame of SEQUENCE_DIR in order (the server "
                    "keeps the temporal history), write each output to OUT/frame_NNNN.exr and print per-frame "
                    "timings (server inference, whole server request, client round trip) and a summary. The "
                    "frames go over one WebSocket as raw arrays (--transport http: one POST per frame, as an EXR). "
                    "The session is deleted at the end.")
    parser.add_argument("sequence_dir", type=Path, metavar="SEQUENCE_DIR",
                        help="sequence folder (manifest.json + frame EXRs), or a plain folder of a renderer's frame "
                             "EXRs (sent in name order; its other files, a manifest.json of another format "
                             "included, are ignored and named)")
    parser.add_argument("--layout", default=None, metavar="NAME|FILE",
                        help="how the session reads the frames: a built-in layout (denoiser, blender-cycles, "
                             "generic) or a layout file (.toml, .json); default denoiser")
    parser.add_argument("--model", required=True, metavar="NAME",
                        help="registered model, pretrained model (denoiser pretrained), or a method without weights "
                             "(oidn:high, oidn-taa, svgf, accumulation)")
    parser.add_argument("--scale", type=int, choices=(1, 2), default=None,
                        help="a method's output scale (default 1); a model runs at its own")
    which = parser.add_mutually_exclusive_group()
    which.add_argument("--version", default=None, help="model version (default: the latest)")
    which.add_argument("--alias", default=None, help="model alias, e.g. champion")
    parser.add_argument("--out", type=Path, required=True, metavar="DIR", help="folder for the output EXRs")
    parser.add_argument("--on-gap", choices=("reset", "reject"), default="reset",
                        help="what the session does when a frame index is skipped")
    parser.add_argument("--keep-references", action="store_true",
                        help="send frames as they are on disk (default: re-encode without the ignored references)")
    parser.add_argument("--keep-session", action="store_true", help="do not delete the session at the end")
    parser.add_argument("--transport", choices=("websocket", "http"), default="websocket",
                        help="websocket (default): the frames go as raw arrays over one WebSocket, read here (a plain "
                             "folder in --layout); http: each frame is POSTed as an EXR file, for the session to "
                             "read")
    parser.add_argument("--png", action="store_true",
                        help="also write OUT/frame_NNNN.png, display-encoded (clip(x, 0, 1) ** (1/2.2), 8 bit)")
    parser.add_argument("--quiet", action="store_true", help="print only the summary")
    parser.set_defaults(run=_talks_to_server(_run_stream))


def _run_stream(args) -> int:
    from client.frames import FrameFileError, is_sequence_folder, renderer_frame_files, sequence_frame_files
    from model.layouts import BUILTIN_LAYOUTS, LayoutError, read_layout_file

    if not args.sequence_dir.is_dir():
        raise UsageError(f"{args.sequence_dir} is not a folder")
    if args.out.exists() and not args.out.is_dir():
        raise UsageError(f"--out {args.out} is a file; give a folder")
    try:  # only this project's manifest makes a sequence folder; a renderer's own is one more file to ignore
        if is_sequence_folder(args.sequence_dir):
            frames = len(sequence_frame_files(args.sequence_dir)[0])
        else:
            frames = len(renderer_frame_files(args.sequence_dir)[0])
    except FrameFileError as error:
        raise UsageError(str(error)) from None
    layout = args.layout
    if layout is not None and layout not in BUILTIN_LAYOUTS:
        try:  # a file: the session gets the layout itself (the server cannot read the client's files)
            layout = read_layout_file(layout) if layout.endswith((".toml", ".json")) else layout
        except LayoutError as error:
            raise UsageError(str(error)) from None
        if isinstance(layout, str):
            raise UsageError(f"--layout {layout}: not a built-in layout ({', '.join(BUILTIN_LAYOUTS)}) nor a "
                             f"layout file (.toml, .json)")

    def report(info, path) -> None:
        if not args.quiet:
            print(f"frame {info.frame_index if info.frame_index is not None else '?':>4}  "
                  f"inference {_ms(info.inference_ms)}  server {_ms(info.server_ms)}  "
                  f"round trip {_ms(info.round_trip_ms)}  {info.history or '-':<16} {path.name}"
                  + (f"  (server repaired {info.sanitized_pixels} input pixels: "
                     f"{info.headers.get('X-Sanitized', '')})" if info.sanitized_pixels else "")
                  + (f"  (ignored channels: {info.headers['X-Ignored-Channels']})"
                     if info.headers.get("X-Ignored-Channels") else "")
                  + (f"  (repaired: {info.headers['X-Repairs']})" if info.headers.get("X-Repairs") else ""),
                  flush=True)

    with _client(args) as client:
        session = client.create_session(args.model, version=args.version, alias=args.alias, on_gap=args.on_gap,
                                        layout=layout, scale=args.scale)
        model = session.get("model") or {}
        which = {"method": "method", "pretrained": "pretrained"}.get(model.get("source"),
                                                                     f"version {model.get('version', '?')}")
        print(f"session {session.get('id')}: {model.get('name', args.model)} {which} "
              f"({model.get('method', '?')}{':' + model['preset'] if model.get('preset') else ''}, "
              f"scale {model.get('scale', '?')}), {frames} frames", flush=True)
        try:
            summary = client.stream_sequence(session["id"], args.sequence_dir, args.out,
                                             strip_references=not args.keep_references, on_frame=report,
                                             transport=args.transport, layout=layout, png=args.png)
        finally:
            if not args.keep_session:
                _delete_quietly(client, session["id"])
    numbers = summary.as_dict()
    print(f"{numbers['frames']} frames in {numbers['wall_seconds']:.2f} s ({numbers['frames_per_second']} fps); "
          f"median inference {_ms(numbers['median_inference_ms'])}, server {_ms(numbers['median_server_ms'])}, "
          f"round trip {_ms(numbers['median_round_trip_ms'])}; history: "
          + ", ".join(f"{k} {v}" for k, v in numbers["history"].items()))
    if summary.ignored:
        shown = ", ".join(summary.ignored[:5]) + (f" and {len(summary.ignored) - 5} more" if len(summary.ignored) > 5
                                                  else "")
        print(f"ignored {len(summary.ignored)} file(s) that are not frames: {shown}", file=sys.stderr)
    print(f"wrote {len(summary.files)} EXR(s)" + (f" and {len(summary.pngs)} PNG(s)" if summary.pngs else "")
          + f" to {args.out}")
    return 0


def _delete_quietly(client, session_id: str) -> None:
    """End the session; a failure here must not hide the streaming error that may be propagating."""
    from client.rest import ApiClientError, ServerUnreachable

    try:
        client.delete_session(session_id)
    except (ApiClientError, ServerUnreachable) as error:
        print(f"warning: could not delete session {session_id}: {error}", file=sys.stderr)


def _ms(value) -> str:
    return "     -  " if value is None else f"{value:7.2f} ms"


# ----------------------------------------------------------------------------------------------- tables

def _print_table(header: tuple[str, ...], rows: list[tuple], empty: str = "none") -> None:
    if not rows:
        print(empty)
        return
    table = [header] + [tuple("" if cell is None else str(cell) for cell in row) for row in rows]
    widths = [max(len(line[column]) for line in table) for column in range(len(header))]
    for line in table:
        print("  ".join(cell.ljust(width) for cell, width in zip(line, widths)).rstrip())
