"""docker-compose.yml: valid against the compose specification, offline; its commands are the
ones tests/test_distributed.py runs (it builds them from this file: see helpers.compose_command)."""

from __future__ import annotations

import subprocess
import sys
from pathlib import Path

import yaml

from helpers import ROOT, compose_command, compose_services

CHECK = Path(sys.executable).parent / "check-jsonschema"


def _validate(path: Path) -> subprocess.CompletedProcess:
    return subprocess.run([CHECK, "--builtin-schema", "vendor.compose-spec", str(path)],
                          capture_output=True, text=True, timeout=120)


def test_the_compose_file_follows_the_compose_specification(tmp_path):
    result = _validate(ROOT / "docker-compose.yml")
    assert result.returncode == 0, result.stdout + result.stderr
    # the check can fail: a misspelt service key, volumes that are not a list
    for key, value in (("comand", "btf run"), ("volumes", "data:/data")):
        spec = yaml.safe_load((ROOT / "docker-compose.yml").read_text())
        spec["services"]["runner"][key] = value
        broken = tmp_path / "docker-compose.yml"
        broken.write_text(yaml.safe_dump(spec))
        result = _validate(broken)
        assert result.returncode != 0 and key in result.stdout, result.stdout


def test_the_services_run_the_commands_the_cluster_tests_run():
    services = compose_services()
    assert set(services) == {"scheduler", "worker", "runner"}
    assert compose_command("scheduler")[:2] == ["dask", "scheduler"]
    worker = compose_command("worker")
    assert worker[:3] == ["dask", "worker", "tcp://scheduler:8786"]
    assert "--memory-limit" in worker  # each worker's memory is bounded (README: how to set it)
    runner = compose_command("runner")
    assert runner[:2] == ["btf", "run"] and runner[-2:] == ["--scheduler", "tcp://scheduler:8786"]
    assert (ROOT / runner[2].removeprefix("/app/")).is_file()  # the image copies configs/ to /app
    # every container that reads or writes stores mounts the shared volume at the same path
    for name in ("worker", "runner"):
        assert "data:/data" in services[name]["volumes"]
    dockerfile = (ROOT / "Dockerfile").read_text()
    assert "WORKDIR /data" in dockerfile and "COPY configs ./configs" in dockerfile
