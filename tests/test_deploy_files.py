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
    """Accepted with both secrets; refused without either; the secrets' values reach no
    container's command line, and the API is published on loopback only."""
    config = ["docker-compose", "-f", str(REPO / "docker-compose.yml"), "config"]
    env = {k: v for k, v in os.environ.items() if k not in ("REDIS_PASSWORD", "PHOTONFARM_TOKEN")}
    secrets = {"REDIS_PASSWORD": "pw-value", "PHOTONFARM_TOKEN": "token-value"}
    for missing in secrets:
        given = {k: v for k, v in secrets.items() if k != missing}
        unset = subprocess.run(config, capture_output=True, text=True, cwd=REPO, env={**env, **given})
        assert unset.returncode != 0 and missing in unset.stderr, unset.stderr  # no service without it
    proc = subprocess.run(config, capture_output=True, text=True, cwd=REPO, env={**env, **secrets})
    assert proc.returncode == 0, proc.stderr
    services = yaml.safe_load(proc.stdout)["services"]
    assert set(services) == {"redis", "api", "reducer", "worker"}
    for name in ("api", "reducer", "worker"):
        assert services[name]["environment"]["REDIS_URL"] == "redis://:pw-value@redis:6379/0"
    assert services["api"]["environment"]["PHOTONFARM_TOKEN"] == "token-value"
    assert services["api"]["ports"] == ["127.0.0.1:8000:8000/tcp"] and "ports" not in services["redis"]
    for name, service in services.items():
        argv = " ".join(str(a) for a in [*service.get("entrypoint", []), *service.get("command", [])])
        assert "pw-value" not in argv and "token-value" not in argv and "--requirepass" not in argv, name
    assert services["worker"]["command"] == ["photonfarm", "worker"]
    assert services["reducer"]["command"] == ["photonfarm", "reducer"]
    assert services["api"]["command"][-2:] == ["--reducers", "0"]  # the reducer service folds


def test_readme_starts_with_the_two_setup_commands() -> None:
    head = (REPO / "README.md").read_text().splitlines()[:5]
    assert any(line.strip().startswith("make serve") for line in head)
    assert any(line.strip().startswith("make test") for line in head)
    assert "make test" in (REPO / ".ci" / "run").read_text()
