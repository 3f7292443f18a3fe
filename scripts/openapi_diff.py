"""What a change removed from the REST API: paths, operations, response codes, schemas and fields.

Compares two OpenAPI documents (JSON files, or ``app`` for this checkout's app) and lists every path, operation,
response status, component schema, field, enum value and parameter that the old one has and the new one lacks,
and every field that became required. Descriptions and additions never count. Exit status 1 when anything was
removed, 0 otherwise, 2 for unreadable input.

    .venv/bin/python scripts/openapi_diff.py old.json app          # old spec (git stash of main, say) vs now
    .venv/bin/python scripts/openapi_diff.py app --write now.json  # save this checkout's spec
"""

from __future__ import annotations

import argparse
import json
import sys
from pathlib import Path
from typing import Any

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

METHODS = ("get", "put", "post", "delete", "patch", "head", "options")


def load(source: str) -> dict[str, Any]:
    if source == "app":
        from service.http.app import create_app

        return create_app().openapi()
    return json.loads(Path(source).read_text())


def removals(old: dict[str, Any], new: dict[str, Any]) -> list[str]:
    """One line per thing ``old`` offers that ``new`` does not (a breaking change for a client)."""
    found: list[str] = []
    old_paths, new_paths = old.get("paths", {}), new.get("paths", {})
    for path, operations in old_paths.items():
        if path not in new_paths:
            found.append(f"path removed: {path}")
            continue
        for method in METHODS:
            if method not in operations:
                continue
            where = f"{method.upper()} {path}"
            if method not in new_paths[path]:
                found.append(f"operation removed: {where}")
                continue
            found += _operation_removals(where, operations[method], new_paths[path][method])
    old_schemas = old.get("components", {}).get("schemas", {})
    new_schemas = new.get("components", {}).get("schemas", {})
    for name, schema in old_schemas.items():
        if name not in new_schemas:
            found.append(f"schema removed: {name}")
            continue
        found += _schema_removals(name, schema, new_schemas[name])
    return found


def _operation_removals(where: str, old: dict[str, Any], new: dict[str, Any]) -> list[str]:
    found = [f"response removed: {where} -> {status}" for status in old.get("responses", {})
             if status not in new.get("responses", {})]
    new_parameters = {(p.get("in"), p.get("name")): p for p in new.get("parameters", [])}
    for parameter in old.get("parameters", []):
        key = (parameter.get("in"), parameter.get("name"))
        if key not in new_parameters:
            found.append(f"parameter removed: {where} {key[0]} {key[1]}")
        elif new_parameters[key].get("required") and not parameter.get("required"):
            found.append(f"parameter became required: {where} {key[0]} {key[1]}")
    return found


def _schema_removals(name: str, old: dict[str, Any], new: dict[str, Any]) -> list[str]:
    found = [f"field removed: {name}.{field}" for field in old.get("properties", {})
             if field not in new.get("properties", {})]
    found += [f"field became required: {name}.{field}" for field in new.get("required", [])
              if field not in old.get("required", []) and field in old.get("properties", {})]
    if "enum" in old:
        found += [f"enum value removed: {name} {value!r}" for value in old["enum"] if value not in new.get("enum", [])]
    for field, spec in old.get("properties", {}).items():
        if field in new.get("properties", {}) and "enum" in spec:
            kept = new["properties"][field].get("enum", [])
            found += [f"enum value removed: {name}.{field} {value!r}" for value in spec["enum"] if value not in kept]
    return found


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("old", help="an OpenAPI JSON file, or 'app' for this checkout's app")
    parser.add_argument("new", nargs="?", default=None, help="the same (omit with --write)")
    parser.add_argument("--write", type=Path, metavar="FILE", help="write OLD's document to FILE and stop")
    args = parser.parse_args(argv)
    try:
        old = load(args.old)
        if args.write is not None:
            args.write.write_text(json.dumps(old, indent=1, sort_keys=True))
            return 0
        if args.new is None:
            parser.error("give NEW, or --write FILE")
        new = load(args.new)
    except (OSError, json.JSONDecodeError) as error:
        print(f"openapi_diff: {error}", file=sys.stderr)
        return 2
    lines = removals(old, new)
    for line in lines:
        print(line)
    print(f"{len(lines)} removal(s)" if lines else "nothing removed")
    return 1 if lines else 0


if __name__ == "__main__":
    sys.exit(main())
