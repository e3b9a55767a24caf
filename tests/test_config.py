"""The configuration (worker/config.py): every variable parsed to its field's type, a bad
value refused in one line that names the variable (and never echoes a secret), a secret
read from the file its _FILE variable names, and the CLI stopping on a bad variable
before it starts anything."""

from __future__ import annotations

import dataclasses
import os
import subprocess
from pathlib import Path

import pytest

from tests.helpers import PHOTONFARM
from worker.config import VARIABLES, Config, ConfigError


def test_an_empty_environment_gives_the_declared_defaults() -> None:
    assert Config.from_environ({}) == Config()
    assert Config.from_environ({v.name: "" for v in VARIABLES}) == Config()  # empty counts as unset
    assert [v.field for v in VARIABLES] == [f.name for f in dataclasses.fields(Config)]


def test_values_take_their_fields_types() -> None:
    c = Config.from_environ({"PHOTONFARM_LEASE_SECONDS": "2.5", "PHOTONFARM_TILE_PIXELS": "2048",
                             "PHOTONFARM_STATE_URLS": "redis://a:1/0, redis://b:2/0,", "PHOTONFARM_DATA": "/srv/pf",
                             "PHOTONFARM_TILE_CACHE_MB": "1.5", "REDIS_URL": "unix:///run/redis.sock"})
    assert (c.lease_seconds, c.tile_pixels, c.state_urls) == (2.5, 2048, ("redis://a:1/0", "redis://b:2/0"))
    assert (c.data, c.tile_cache_bytes, c.redis_url) == (Path("/srv/pf"), 1_500_000, "unix:///run/redis.sock")
    assert (c.alive_seconds, c.fold_lease_seconds, c.queued_seconds) == (7.5, 2.5, 2.5)  # derived, they follow


@pytest.mark.parametrize(("name", "value"), [
    ("PHOTONFARM_LEASE_SECONDS", "-1"), ("PHOTONFARM_LEASE_SECONDS", "nan"), ("PHOTONFARM_LEASE_SECONDS", "30s"),
    ("PHOTONFARM_TILE_PIXELS", "1.5"), ("PHOTONFARM_TILE_PIXELS", "0"), ("PHOTONFARM_MERGE_SHARE", "2"),
    ("PHOTONFARM_HOST_THREADS", "many"),
])
def test_a_bad_value_is_one_line_naming_the_variable(name: str, value: str) -> None:
    with pytest.raises(ConfigError) as info:
        Config.from_environ({name: value})
    message = str(info.value)
    assert message.startswith(f"{name}: expected ") and "\n" not in message and repr(value) in message


def test_a_bad_secret_is_named_but_not_shown(tmp_path: Path) -> None:
    for name, value in (("REDIS_URL", "http://:hunter2@example"), ("PHOTONFARM_STATE_URLS", "redis://x, hunter2")):
        with pytest.raises(ConfigError, match=f"^{name}: expected") as info:
            Config.from_environ({name: value})
        assert "hunter2" not in str(info.value)


def test_secrets_come_from_the_files_their_file_variables_name(tmp_path: Path) -> None:
    token, url = tmp_path / "token", tmp_path / "url"
    token.write_text("t0ken\n")
    url.write_text("redis://:pw@db:6379/0\n")
    c = Config.from_environ({"PHOTONFARM_TOKEN_FILE": str(token), "REDIS_URL_FILE": str(url)})
    assert (c.token, c.redis_url) == ("t0ken", "redis://:pw@db:6379/0")
    with pytest.raises(ConfigError, match="^PHOTONFARM_TOKEN and PHOTONFARM_TOKEN_FILE are both set"):
        Config.from_environ({"PHOTONFARM_TOKEN": "x", "PHOTONFARM_TOKEN_FILE": str(token)})
    with pytest.raises(ConfigError, match="^PHOTONFARM_TOKEN_FILE: cannot read"):
        Config.from_environ({"PHOTONFARM_TOKEN_FILE": str(tmp_path / "missing")})
    (tmp_path / "empty").write_text("\n")
    with pytest.raises(ConfigError, match="^PHOTONFARM_TOKEN_FILE: .* is empty"):
        Config.from_environ({"PHOTONFARM_TOKEN_FILE": str(tmp_path / "empty")})
    assert Config.from_environ({"PHOTONFARM_URL_FILE": str(token)}) == Config()  # not a secret: no _FILE form


def test_the_cli_stops_on_a_bad_variable_before_it_starts() -> None:
    env = {**os.environ, "PHOTONFARM_LEASE_SECONDS": "soon"}
    for args in (["worker", "--burst"], ["serve", "--workers", "0"]):
        proc = subprocess.run([str(PHOTONFARM), *args], capture_output=True, text=True, timeout=60, env=env)
        assert proc.returncode == 2, proc.stderr
        assert proc.stderr.strip() == "photonfarm: PHOTONFARM_LEASE_SECONDS: expected seconds, a positive number: " \
                                      "got 'soon'", proc.stderr
