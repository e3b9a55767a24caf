"""The generated reference stays true to the code: every PHOTONFARM_* variable the code
reads is declared in worker/environment.py and every declared one is read, the
settings table the docs hook builds names every Settings field with its default, and the
job notes' cap is in the limits table and the job view's reference."""

from __future__ import annotations

import importlib.util
import json
import re
from pathlib import Path
from types import ModuleType

from worker.environment import VARIABLES
from worker.settings import Settings
from worker.store.record import MAX_JOB_NOTES, MAX_NOTE_CHARS

ROOT = Path(__file__).resolve().parent.parent
NAME = re.compile(r"PHOTONFARM_[A-Z_]+")
HOOK = ROOT / "docs" / "hooks" / "reference.py"


def _hook() -> ModuleType:
    """docs/hooks/reference.py, loaded by path as MkDocs loads it."""
    spec = importlib.util.spec_from_file_location("reference_hook", HOOK)
    assert spec is not None and spec.loader is not None
    module = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(module)
    return module


def _used_names() -> dict[str, list[str]]:
    """Every PHOTONFARM_* name in the code, with the files it appears in (the declaration excluded)."""
    files = [p for d in ("worker", "service", "kernels") for p in (ROOT / d).rglob("*.py")]
    files.append(ROOT / "docker-compose.yml")
    used: dict[str, list[str]] = {}
    for path in files:
        if path == ROOT / "worker" / "environment.py":
            continue
        for name in set(NAME.findall(path.read_text())):
            used.setdefault(name, []).append(str(path.relative_to(ROOT)))
    return used


def test_every_environment_variable_is_declared_and_used() -> None:
    declared = {v.name for v in VARIABLES}
    used = _used_names()
    assert len(declared) == len(VARIABLES), "a variable is declared twice"
    missing = {name: where for name, where in used.items() if name not in declared}
    assert not missing, f"read by the code but not declared in worker/environment.py: {missing}"
    unused = declared - used.keys()
    assert not unused, f"declared in worker/environment.py but no longer in the code: {sorted(unused)}"


def test_environment_table_lists_every_variable_with_its_default() -> None:
    table = _hook().environment_table()
    for v in VARIABLES:
        row = next((line for line in table.splitlines() if line.startswith(f"| `{v.name}` |")), None)
        assert row is not None, f"{v.name} missing from the environment table"
        assert (f"`{v.default}`" if v.default is not None else "unset") in row


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
