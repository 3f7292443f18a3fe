"""`denoiser pretrained`: the models shipped in pretrained/, their held-out scores, and registering them in MLflow."""

from __future__ import annotations

from cli.main import UsageError


def add_commands(commands) -> None:
    parser = commands.add_parser(
        "pretrained", help="list the pretrained models shipped with the project (held-out scores); --register them",
        description="List the pretrained models in pretrained/ (model/deployment/pretrained.py): method, scale, training "
                    "steps, the held-out PSNR and FLIP next to OIDN-high and OIDN + TAA (high) of the same "
                    "evaluation run, and whether the weights pass their sha256 check. --register registers each "
                    "one in the MLflow registry under its name with an alias (default 'pretrained'), once: "
                    "running it again finds the version with the same sha256 and only re-points the alias.")
    parser.add_argument("--register", action="store_true", help="register them in the MLflow registry")
    parser.add_argument("--alias", default="pretrained", help="alias the registered versions get (default: pretrained)")
    parser.add_argument("--tracking-uri", default=None, metavar="URI",
                        help="MLflow tracking URI; none given: the service's ($DENOISER_TRACKING_URI, else "
                             "sqlite under $DENOISER_DATA_DIR/mlflow)")
    parser.add_argument("--markdown", action="store_true",
                        help="print the held-out table as Markdown (each model's rows: it, OIDN, OIDN + TAA) instead")
    parser.set_defaults(run=_run_pretrained)


def _same_quality_taa(model) -> str:
    """OIDN + TAA's held-out PSNR at the model's OIDN quality (a fused preset is one), else at high, with the
    quality: the bar each shipped model is held to."""
    from model.deployment.pretrained import peer_row, score_text
    from model.methods.oidn import QUALITIES

    quality = model.preset if model.preset in QUALITIES else "high"
    score = score_text(peer_row(model, f"oidn-taa:{quality}"), "psnr", ".2f")
    return score if score == "-" else f"{score} ({quality})"


def _run_pretrained(args) -> int:
    from core.registry import pretrained_dir
    from model.deployment.pretrained import (
        PretrainedError,
        get_pretrained,
        held_out_markdown,
        peer_row,
        pretrained_names,
        score_text,
        verify,
    )
    from cli.commands.client import _print_table

    root = pretrained_dir()
    if args.markdown:
        print(held_out_markdown([get_pretrained(name, root) for name in pretrained_names(root)]))
        return 0

    rows, broken, models = [], [], []
    for name in pretrained_names(root):
        try:
            model = get_pretrained(name, root)
            verify(model)
            check = "ok"
        except PretrainedError as error:
            broken.append(str(error))
            rows.append((name, "-", "-", "-", "-", "-", "-", "-", "-", "DAMAGED"))
            continue
        models.append(model)
        training = model.manifest.get("training") or {}
        own = model.held_out_row()
        rows.append((name, f"{model.method}:{model.preset}", model.scale, model.manifest.get("params", "-"),
                     training.get("step", "-"), score_text(own, "psnr", ".2f"), score_text(own, "flip", ".4f"),
                     score_text(peer_row(model, "oidn:high"), "psnr", ".2f"), _same_quality_taa(model),
                     check if own else f"{check}, held-out pending"))
    _print_table(("name", "method", "scale", "params", "steps", "held-out PSNR", "FLIP", "OIDN-high PSNR",
                  "OIDN+TAA PSNR (quality)", "weights"), rows, empty="no pretrained models in pretrained/")
    for model in models:
        if model.manifest.get("note"):
            print(f"{model.name}: {model.manifest['note']}")
    for message in broken:
        print(f"error: {message}")
    if args.register:
        from core.settings import get_settings
        from core.tracking import register_pretrained

        uri = args.tracking_uri or get_settings().resolved_tracking_uri()
        for model in models:
            result = register_pretrained(model, uri, alias=args.alias)
            what = "registered as" if result["created"] else "already registered as"
            print(f"{model.name}: {what} version {result['version']}; {result['uri']}")
    if broken:
        raise UsageError(f"{len(broken)} pretrained model(s) fail their check (above)")
    return 0
