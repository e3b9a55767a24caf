"""One settings model: the CLI's flags and the API's fields take their defaults from it,
and the API process never loads OpenCL."""

from __future__ import annotations

import subprocess
import sys

from service.cli import RENDER_FIELDS, build_parser
from service.models import JobRequest, JobSettings
from worker.settings import DEFAULT_ALPHA, DEFAULTS, MAX_DEFAULT_SUBPATHS, Settings


def test_cli_and_api_defaults_are_the_models_own() -> None:
    render = build_parser()._subparsers._group_actions[0].choices["render"]
    flags = {a.dest: a for a in render._actions}
    for name in RENDER_FIELDS:
        assert flags[name].default == Settings.model_fields[name].default, name
        assert flags[name].help.startswith(Settings.model_fields[name].description), name
    for name, field in Settings.model_fields.items():
        assert JobSettings.model_fields[name].default == field.default, name
    # what a request without settings gets is exactly the model's defaults
    assert JobRequest(scene_name="furnace").settings.model_dump() == DEFAULTS.model_dump()


def test_the_service_limits_are_tighter_not_different() -> None:
    too_many = Settings.model_fields["photons_per_pass"].metadata
    assert any(getattr(m, "le", 0) > (1 << 22) for m in too_many)
    for value in (1 << 22, 1 << 23):
        assert Settings(photons_per_pass=value).photons_per_pass == value
    try:
        JobSettings(photons_per_pass=1 << 23)
    except ValueError as exc:
        assert "photons_per_pass" in str(exc)
    else:
        raise AssertionError("the service accepted more photons per pass than its limit")


def test_the_api_process_does_not_import_opencl() -> None:
    code = "import sys, service.app, service.metrics, service.models; print('pyopencl' in sys.modules)"
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, check=True)
    assert out.stdout.strip() == "False", out


def test_a_threshold_needs_the_error_estimate() -> None:
    try:
        Settings(error_threshold=0.1, error_estimation=False)
    except ValueError as exc:
        assert "error_estimation" in str(exc)
    else:
        raise AssertionError("a threshold without an error estimate can never be reached")


def test_alpha_defaults_by_method() -> None:
    """No alpha given: the method's (DEFAULT_ALPHA, one place); a given alpha wins; the
    settings a job stores hold the alpha it renders with, so a stored job keeps it."""
    assert set(DEFAULT_ALPHA) == set(Settings.model_fields["method"].annotation.__args__)
    for method, alpha in DEFAULT_ALPHA.items():
        settings = Settings(method=method)
        assert settings.alpha == alpha
        assert Settings.model_validate(settings.model_dump()).alpha == alpha
        assert JobRequest(scene_name="furnace", settings={"method": method}).settings.alpha == alpha
        assert Settings(method=method, alpha=0.55).alpha == 0.55
    assert DEFAULT_ALPHA["vcm"] < 2.0 / 3.0  # chapter 9: the merging radius's bias leaves the MIS weights
    render = build_parser()._subparsers._group_actions[0].choices["render"]
    alpha_help = next(a.help for a in render._actions if a.dest == "alpha")
    assert all(f"{method} {alpha:g}" in alpha_help for method, alpha in DEFAULT_ALPHA.items())


def test_paths_per_pass_default_by_frame() -> None:
    """No count given: every method traces one path per pixel (capped); a given count wins; a
    frame's settings keep the count and the resolution they render with."""
    for method in ("sppm", "ppm", "vcm", "bpt", "lt"):
        framed = Settings(method=method).for_frame(64, 32)
        assert framed.paths_per_pass == 64 * 32 and framed.resolution == (64, 32)
        assert Settings(method=method).for_frame(4096, 4096).paths_per_pass == MAX_DEFAULT_SUBPATHS
        assert Settings(method=method, photons_per_pass=5).for_frame(64, 32).paths_per_pass == 5
    assert Settings(resolution=(8, 8)).for_frame(64, 32).resolution == (8, 8)
    try:
        _ = Settings().paths_per_pass
    except ValueError as exc:
        assert "for_frame" in str(exc)
    else:
        raise AssertionError("settings without a frame gave a path count")
