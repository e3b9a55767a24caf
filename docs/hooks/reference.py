"""MkDocs hook: the reference tables, generated from the code at build time.

A page asks for a table with a marker line (`<!-- generated: NAME -->`, NAME one of
GENERATORS); the marker is replaced by the table. The settings table comes from the
`Settings` model (worker/settings.py), the environment table from worker/environment.py,
the HTTP reference from the app's OpenAPI schema (service/app.py): the docs never retype
them. tests/test_reference_docs.py checks these same functions against the code.
"""

from __future__ import annotations

import json
import re
from collections.abc import Callable
from typing import Any

from worker.environment import VARIABLES
from worker.scene import MAX_PIXELS, MAX_RESOLUTION
from worker.settings import DEFAULT_MAX_SECONDS, Settings

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
             f"`initial_radius` is derived from the scene; `resolution` is the scene's, each side in "
             f"1..{MAX_RESOLUTION} and at most {MAX_PIXELS:,} pixels (the service allows fewer, see Limits).")
    return head + "\n".join(settings_rows().values()) + notes


def environment_table() -> str:
    """Every PHOTONFARM_* variable: name, default, format, meaning, the module that reads it."""
    head = "| variable | default | format | meaning | read by |\n|---|---|---|---|---|\n"
    return head + "\n".join(
        "| " + " | ".join(_cell(c) for c in (
            f"`{v.name}`", f"`{v.default}`" if v.default is not None else "unset", v.format, v.meaning,
            ", ".join(f"`{m.strip()}`" for m in v.read_by.split(",")))) + " |"
        for v in VARIABLES)


def openapi_schema() -> dict[str, Any]:
    """The service's OpenAPI schema, as `GET /openapi.json` serves it (no token set)."""
    from service.app import create_app

    return create_app(UNUSED_REDIS_URL, reaper=False).openapi()


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
}


def on_page_markdown(markdown: str, **_: Any) -> str:
    """Replace every marker line with its generated Markdown."""
    return MARKER.sub(lambda m: GENERATORS[m.group(1)](), markdown)
