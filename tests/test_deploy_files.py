"""The deployment files are accepted by their tools."""

from __future__ import annotations

import os
import shutil
import subprocess
from pathlib import Path

import pytest
import yaml

REPO = Path(__file__).resolve().parent.parent


@pytest.mark.skipif(shutil.which("docker-compose") is None,
                    reason="Debian's docker-compose is not installed here (.ci/run installs it)")
def test_docker_compose_config_is_valid() -> None:
    config = ["docker-compose", "-f", str(REPO / "docker-compose.yml"), "config"]
    env = {k: v for k, v in os.environ.items() if k != "REDIS_PASSWORD"}
    unset = subprocess.run(config, capture_output=True, text=True, cwd=REPO, env=env)
    assert unset.returncode != 0 and "REDIS_PASSWORD" in unset.stderr  # no Redis without a password
    proc = subprocess.run(config, capture_output=True, text=True, cwd=REPO, env={**env, "REDIS_PASSWORD": "pw"})
    assert proc.returncode == 0, proc.stderr
    services = yaml.safe_load(proc.stdout)["services"]
    assert set(services) == {"redis", "api", "worker"}
    for name in ("api", "worker"):
        assert services[name]["environment"]["REDIS_URL"] == "redis://:pw@redis:6379/0"
    assert "--requirepass" in services["redis"]["command"] and "ports" not in services["redis"]
    assert services["worker"]["command"] == ["photonfarm", "worker"]


def test_readme_starts_with_the_two_setup_commands() -> None:
    head = (REPO / "README.md").read_text().splitlines()[:5]
    assert any(line.strip().startswith("make serve") for line in head)
    assert any(line.strip().startswith("make test") for line in head)
    assert "make test" in (REPO / ".ci" / "run").read_text()
