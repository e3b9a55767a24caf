"""The generated reference stays true to the code: every PHOTONFARM_* and REDIS_* variable
the code, the deployment files and the docs name is declared in worker/config.py, every
declared one is read through the configuration and no module reads one itself, the
settings table the docs hook builds names every Settings field with its default, and the
job notes' cap is in the limits table and the job view's reference."""

from __future__ import annotations

import importlib.util
import json
import re
from pathlib import Path
from types import ModuleType

from worker.config import FILE_SUFFIX, VARIABLES
from worker.settings import Settings
from worker.store.record import MAX_JOB_NOTES, MAX_NOTE_CHARS

ROOT = Path(__file__).resolve().parent.parent
NAME = re.compile(r"\b(?:PHOTONFARM|REDIS)_[A-Z_]+")
HOOK = ROOT / "docs" / "hooks" / "reference.py"
DECLARATION = ROOT / "worker" / "config.py"
CODE = [p for d in ("worker", "service", "kernels") for p in (ROOT / d).rglob("*.py") if p != DECLARATION]
# A variable read other than through the configuration: os.environ[...], .get(...), getenv(...).
DIRECT_READ = re.compile(r"(?:environ\s*(?:\[|\.get\()|getenv\()\s*[\"']((?:PHOTONFARM|REDIS)_[A-Z_]+)")
NOT_OURS = {"REDIS_PASSWORD"}  # the compose Redis's own password variable (docker-compose.yml)


def _hook() -> ModuleType:
    """docs/hooks/reference.py, loaded by path as MkDocs loads it."""
    spec = importlib.util.spec_from_file_location("reference_hook", HOOK)
    assert spec is not None and spec.loader is not None
    module = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(module)
    return module


def _named() -> dict[str, list[str]]:
    """Every variable name in the code, the deployment files and the docs, with where it appears."""
    files = [*CODE, ROOT / "docker-compose.yml", ROOT / "Dockerfile", *(ROOT / "docs").glob("*.md")]
    named: dict[str, list[str]] = {}
    for path in files:
        for name in set(NAME.findall(path.read_text())):
            named.setdefault(name, []).append(str(path.relative_to(ROOT)))
    return named


def test_every_environment_variable_is_declared_and_read_through_the_configuration() -> None:
    declared = {v.name for v in VARIABLES} | {v.name + FILE_SUFFIX for v in VARIABLES if v.secret}
    assert len({v.name for v in VARIABLES}) == len(VARIABLES), "a variable is declared twice"
    missing = {name: where for name, where in _named().items() if name not in declared | NOT_OURS}
    assert not missing, f"named but not declared in worker/config.py: {missing}"
    code = "\n".join(p.read_text() for p in [*CODE, DECLARATION])  # the declaration's derived properties too
    unread = [v.field for v in VARIABLES if not re.search(rf"\.{v.field}\b", code)]
    assert not unread, f"fields of Config nothing reads: {unread}"
    direct = {str(p.relative_to(ROOT)): DIRECT_READ.findall(p.read_text()) for p in CODE}
    assert not {p: names for p, names in direct.items() if names}, "read from the environment, not config()"


def test_environment_table_lists_every_variable_with_its_default() -> None:
    table = _hook().environment_table()
    for v in VARIABLES:
        row = next((line for line in table.splitlines() if line.startswith(f"| `{v.name}`")), None)
        assert row is not None, f"{v.name} missing from the environment table"
        assert _hook().shown_default(v.default) in row


def test_settings_table_lists_every_field_with_its_default() -> None:
    table = _hook().settings_table()
    lines = table.splitlines()
    for name, field in Settings.model_fields.items():
        row = next((line for line in lines if line.startswith(f"| `{name}` |")), None)
        assert row is not None, f"setting {name} missing from the generated settings table"
        assert f"`{json.dumps(field.default)}`" in row, f"{name}: default {field.default!r} not in {row}"
        default_by = (field.json_schema_extra or {}).get("x-default-by", {}) if isinstance(
            field.json_schema_extra, dict) else {}
        for table_by in default_by.values():
            for key, value in table_by.items():
                assert f"{key} `{value:g}`" in row, f"{name}: default for {key} missing"
    assert len([line for line in lines if line.startswith("| `")]) == len(Settings.model_fields)


def test_the_job_notes_cap_is_in_the_limits_table_and_the_job_view() -> None:
    hook = _hook()
    row = next((line for line in hook.limits_table().splitlines() if line.startswith("| notes per job |")), None)
    assert row is not None, "the notes cap is missing from the generated limits table"
    assert f"| {MAX_JOB_NOTES} distinct, each at most {MAX_NOTE_CHARS:,} characters |" in row, row
    reference = hook.http_reference()
    view = reference[reference.index("### JobView"):]
    notes = next(line for line in view.splitlines() if line.startswith("| `notes` |"))
    assert f"at most {MAX_JOB_NOTES}" in notes and f"{MAX_NOTE_CHARS} characters" in notes, notes
