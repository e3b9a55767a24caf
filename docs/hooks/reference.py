"""MkDocs hook: the reference tables, generated from the code at build time, and the
benchmark charts.

A page asks for a table with a marker line (`<!-- generated: NAME -->`, NAME one of
GENERATORS); the marker is replaced by the table. The settings table comes from the
`Settings` model (worker/settings.py), the environment table from worker/config.py,
the limits from the constants that enforce them, the HTTP reference from the app's OpenAPI
schema (service/app.py): the docs never retype them. tests/test_reference_docs.py checks
these same functions against the code.
"""

from __future__ import annotations

import json
import re
from collections.abc import Callable
from pathlib import Path
from typing import TYPE_CHECKING, Any

from worker.config import FILE_SUFFIX, VARIABLES, Config
from worker.scene import MAX_PIXELS, MAX_RESOLUTION
from worker.settings import DEFAULT_MAX_SECONDS, Settings

if TYPE_CHECKING:  # the tables need no MkDocs (tests/test_reference_docs.py builds them)
    from mkdocs.config.defaults import MkDocsConfig
    from mkdocs.structure.files import Files

ROOT = Path(__file__).resolve().parents[2]
CHARTS = "bench/out"  # the benchmarks' charts, published at the same path for the results page
MARKER = re.compile(r"^<!-- generated: ([a-z-]+) -->$", re.MULTILINE)
# The app's schema does not depend on the Redis URL (the client connects on first use).
UNUSED_REDIS_URL = "redis://127.0.0.1:1/0"


def _cell(text: str) -> str:
    """Markdown table cell: one line, pipes escaped."""
    return " ".join(text.split()).replace("|", "\\|")


def json_value(value: Any) -> str:
    """A default as the JSON a request would carry, in code style."""
    return f"`{json.dumps(value)}`"


def schema_type(schema: dict[str, Any]) -> str:
    """A JSON-schema node as a short type: `string`, `"a" | "b"`, `integer[]`, [Model](#model)."""
    if "$ref" in schema:
        name = schema["$ref"].rsplit("/", 1)[-1]
        return f"[{name}](#{name.lower()})"
    if "enum" in schema:
        return " | ".join(f"`{json.dumps(v)}`" for v in schema["enum"])
    if "const" in schema:
        return f"`{json.dumps(schema['const'])}`"
    if "anyOf" in schema:
        return " or ".join(schema_type(s) for s in schema["anyOf"])
    kind = schema.get("type", "any")
    if kind == "array":
        if "prefixItems" in schema:
            return "[" + ", ".join(schema_type(s) for s in schema["prefixItems"]) + "]"
        return schema_type(schema.get("items", {})) + "[]"
    if kind == "string" and schema.get("contentMediaType") == "application/octet-stream":
        return "file"
    return str(kind)


def bounds(schema: dict[str, Any]) -> str:
    """The numeric and length bounds of a schema node (and of its anyOf members)."""
    parts: list[str] = []
    for node in [schema, *schema.get("anyOf", [])]:
        for key, sign in (("exclusiveMinimum", ">"), ("minimum", ">="), ("exclusiveMaximum", "<"),
                          ("maximum", "<="), ("minLength", "length >="), ("maxLength", "length <=")):
            if key in node:
                parts.append(f"{sign} {node[key]:g}" if isinstance(node[key], float) else f"{sign} {node[key]}")
        if "pattern" in node:
            parts.append(f"`{node['pattern']}`")
    return ", ".join(parts)


def settings_rows() -> dict[str, str]:
    """One Markdown table row per `Settings` field, by field name."""
    properties = Settings.model_json_schema()["properties"]
    rows: dict[str, str] = {}
    for name, field in Settings.model_fields.items():
        prop = properties[name]
        default = json_value(field.default)
        by = prop.get("x-default-by")
        if by:
            key, table = next(iter(by.items()))
            default += " (then by " + key + ": " + ", ".join(f"{k} `{v:g}`" for k, v in table.items()) + ")"
        rows[name] = "| " + " | ".join(_cell(c) for c in (
            f"`{name}`", schema_type(prop), default, bounds(prop), prop.get("description", ""))) + " |"
    return rows


def settings_table() -> str:
    """Every job setting: name, type or choices, default, bounds, meaning."""
    head = "| setting | type or choices | default | bounds | meaning |\n|---|---|---|---|---|\n"
    notes = (f"\n\n`null` defaults: `alpha` takes its method's value (`x-default-by` in the schema); with "
             f"neither `max_passes` nor `max_seconds`, `max_seconds` is {DEFAULT_MAX_SECONDS:g}; "
             f"`photons_per_pass` is the method's (its meaning says the rule); "
             f"`initial_radius` is derived from the scene; `resolution` is the scene's, each side in "
             f"1..{MAX_RESOLUTION} and at most {MAX_PIXELS:,} pixels (the service allows fewer, see Limits).")
    return head + "\n".join(settings_rows().values()) + notes


def shown_default(value: Any) -> str:
    """A variable's default as the table shows it: its text in code style, or "unset"."""
    if value is None or value == ():
        return "unset"
    return f"`{value:g}`" if isinstance(value, float) else f"`{value}`"


def environment_table() -> str:
    """Every variable of the configuration (worker/config.py): name, default, format, meaning;
    a secret's `_FILE` form beside its name."""
    head = "| variable | default | format | meaning |\n|---|---|---|---|\n"
    return head + "\n".join(
        "| " + " | ".join(_cell(c) for c in (
            f"`{v.name}`" + (f" or `{v.name}{FILE_SUFFIX}`" if v.secret else ""), shown_default(v.default),
            v.format, v.meaning)) + " |"
        for v in VARIABLES)


def limits_table() -> str:
    """Every documented limit, its value read from the constant that enforces it."""
    from service import models, scene_loader, upload
    from worker import scene
    from worker.settings import MAX_PHOTONS_PER_PASS
    from worker.store import record

    defaults = Config()

    rows = [
        ("request body", f"{models.MAX_BODY_BYTES // 2**20} MiB", "413", "bounds the API's memory per request",
         "`service/models.py`"),
        ("pixels per job (service)", f"{models.MAX_SERVICE_PIXELS:,} (3840 x 2160)", "422",
         "the state of the largest job fits the default Redis cap", "`service/models.py`"),
        ("image side / pixels (CLI)", f"{scene.MAX_RESOLUTION:,} / {scene.MAX_PIXELS:,}", "one-line error",
         "bounds device memory per pass", "`worker/scene.py`"),
        ("photons per pass", f"{models.MAX_SERVICE_PHOTONS_PER_PASS:,} service, {MAX_PHOTONS_PER_PASS:,} CLI",
         "422", "bounds device memory and pass time", "`service/models.py`, `worker/settings.py`"),
        ("active jobs at once", f"{models.MAX_ACTIVE_JOBS}", "429", "retry when one ends; checked atomically",
         "`service/models.py`"),
        ("scene name", f"`{scene.SCENE_NAME_PATTERN}`, at most {scene.MAX_SCENE_NAME} characters",
         "422 (404 if unknown)", "a bundled scene's name is never a path", "`worker/scene.py`"),
        ("triangles per scene", f"{scene.MAX_TRIANGLES:,}", "422", "bounds BVH build and memory",
         "`worker/scene.py`"),
        ("shapes / lights", f"{scene.MAX_SHAPES:,} / {scene.MAX_LIGHTS}", "422", "bounds per-pass kernel time",
         "`worker/scene.py`"),
        ("coordinates", f"absolute value at most {scene.MAX_COORD:g}", "422", "keeps float32 positions meaningful",
         "`worker/scene.py`"),
        ("mesh file name", f"at most {scene.MAX_PATH_CHARS} characters, inside the scene's folder", "422",
         "one file-system name, no escape from the root", "`worker/scene.py`"),
        ("scene upload, unpacked", f"{upload.MAX_UPLOAD_BYTES // 2**20} MiB, {upload.MAX_UPLOAD_FILES} entries",
         "413", "each member's declared size checked before it is read, the bytes counted as written: a zip or "
         "tar bomb stops here, named", "`service/upload.py`"),
        ("upload names", f"{upload.MAX_NAME_CHARS:,} characters a path, {upload.MAX_PART_CHARS} a part", "422",
         "what file systems accept", "`service/upload.py`"),
        ("one scene load, in all", ", ".join(f"{v:,} {k.replace('_', ' ')}" for k, v in scene.LOAD_LIMITS.items()),
         "413 naming what ran out and where", "every include and mesh counted each time it is named: a small "
         "upload cannot cost unbounded CPU", "`worker/scene.py` (`LOAD_LIMITS`)"),
        ("XML nesting", f"{scene.MAX_XML_DEPTH} elements deep, includes {scene.MAX_INCLUDE_DEPTH} deep", "422",
         "bounds the converter's work and stack", "`worker/scene.py`"),
        ("scene loads in the API", f"{scene_loader.LOAD_PROCESSES} at once, {scene_loader.LOAD_QUEUE} waiting, "
         f"{scene_loader.LOAD_SECONDS:g} s each", "503", "each in a child process: parsing never holds the "
         "threads that serve requests", "`service/scene_loader.py`"),
        ("notes per job", f"{record.MAX_JOB_NOTES} distinct, each at most {record.MAX_NOTE_CHARS:,} characters",
         "the rest counted in a last line, \"... and N more\"; a longer note cut",
         "bounds the job record, which every poll of the job reads",
         "`worker/store/record.py`"),
        ("batch lease", f"{defaults.lease_seconds:g} s", "re-issue",
         "a batch whose worker stops beating is rendered again", "`PHOTONFARM_LEASE_SECONDS`"),
        ("finished jobs kept", f"{defaults.retention_seconds / 86_400:g} days", "deleted",
         "then deleted with their images", "`PHOTONFARM_RETENTION_SECONDS`"),
        ("state tile", f"{defaults.tile_pixels:,} pixels", "-", "the unit of push, fold and checkpoint",
         "`PHOTONFARM_TILE_PIXELS`"),
    ]
    head = "| what | limit | answer | why | set in |\n|---|---|---|---|---|\n"
    return head + "\n".join("| " + " | ".join(_cell(c) for c in row) + " |" for row in rows)


def openapi_schema() -> dict[str, Any]:
    """The service's OpenAPI schema, as `GET /openapi.json` serves it (no token set)."""
    from service.app import create_app

    return create_app(UNUSED_REDIS_URL).openapi()


def _operation(path: str, method: str, op: dict[str, Any]) -> str:
    out = [f"### {method.upper()} `{path}`", "", op.get("summary", "")]
    if op.get("description"):
        out += ["", " ".join(op["description"].split())]
    params = op.get("parameters", [])
    if params:
        out += ["", "| parameter | in | type | required | default | bounds | meaning |",
                "|---|---|---|---|---|---|---|"]
        for p in params:
            s = p.get("schema", {})
            out.append("| " + " | ".join(_cell(c) for c in (
                f"`{p['name']}`", p["in"], schema_type(s), "yes" if p.get("required") else "no",
                json_value(s["default"]) if "default" in s else "", bounds(s), p.get("description", ""))) + " |")
    body = op.get("requestBody")
    if body:
        for media, content in body["content"].items():
            out += ["", f"Request body ({media}): {schema_type(content['schema'])}"]
    out += ["", "| status | meaning | body |", "|---|---|---|"]
    for code, resp in op["responses"].items():
        content = resp.get("content", {})
        kinds = ", ".join(f"{schema_type(c['schema'])} ({m})" if "schema" in c else m for m, c in content.items())
        out.append(f"| {code} | {_cell(resp.get('description', ''))} | {_cell(kinds)} |")
    return "\n".join(out)


def _model(name: str, schema: dict[str, Any]) -> str:
    out = [f"### {name}", ""]
    if schema.get("description"):
        out += [" ".join(schema["description"].split()), ""]
    if "properties" not in schema:
        out.append(f"Type: {schema_type(schema)}")
        return "\n".join(out)
    required = set(schema.get("required", []))
    out += ["| field | type | required | default | bounds | meaning |", "|---|---|---|---|---|---|"]
    for field, prop in schema["properties"].items():
        out.append("| " + " | ".join(_cell(c) for c in (
            f"`{field}`", schema_type(prop), "yes" if field in required else "no",
            json_value(prop["default"]) if "default" in prop else "", bounds(prop),
            prop.get("description", ""))) + " |")
    return "\n".join(out)


def http_reference() -> str:
    """Every path and method (parameters, request body, responses), then every model."""
    schema = openapi_schema()
    ops = [_operation(path, method, op) for path, item in schema["paths"].items() for method, op in item.items()]
    models = [_model(name, s) for name, s in schema["components"]["schemas"].items()]
    return "## Routes\n\n" + "\n\n".join(ops) + "\n\n## Models\n\n" + "\n\n".join(models)


GENERATORS: dict[str, Callable[[], str]] = {
    "settings": settings_table,
    "environment": environment_table,
    "http-api": http_reference,
    "limits": limits_table,
}


def on_files(files: Files, config: MkDocsConfig) -> Files:
    """Publish bench/out/*.png at bench/out/ in the site, so docs/results.md shows the charts
    where the benchmarks write them, without a copy in docs/."""
    from mkdocs.structure.files import File

    for chart in sorted((ROOT / CHARTS).glob("*.png")):
        files.append(File(f"{CHARTS}/{chart.name}", str(ROOT), config.site_dir, config.use_directory_urls))
    return files


def on_page_markdown(markdown: str, **_: Any) -> str:
    """Replace every marker line with its generated Markdown."""
    return MARKER.sub(lambda m: GENERATORS[m.group(1)](), markdown)
