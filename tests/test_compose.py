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
    assert set(services) == {"s3", "scheduler", "worker", "runner"}
    assert compose_command("scheduler")[:2] == ["dask", "scheduler"]
    worker = compose_command("worker")
    assert worker[:3] == ["dask", "worker", "tcp://scheduler:8786"]
    assert "--memory-limit" in worker  # each worker's memory is bounded (docs/)
    runner = compose_command("runner")
    assert runner[:2] == ["btf", "run"] and runner[-2:] == ["--scheduler", "tcp://scheduler:8786"]
    assert (ROOT / runner[2].removeprefix("/app/")).is_file()  # the image copies configs/ to /app
    # workers and the runner share no volume: only the object store, reached by AWS_* settings
    for name in ("worker", "runner"):
        assert "volumes" not in services[name]
        assert services[name]["environment"]["AWS_ENDPOINT_URL"] == "http://s3:8333"
    config = yaml.safe_load((ROOT / "configs" / "cluster.yaml").read_text())
    outs = [next(iter(s.values())).get("out") for s in config["stages"]]
    assert all(o.startswith("s3://") for o in outs if o)
    assert services["s3"]["command"].split()[:2] == ["server", "-dir=/data"]
    assert "-master.telemetry=false" in services["s3"]["command"]


def test_no_port_of_the_cluster_is_published_on_every_interface():
    """Whoever reaches the scheduler's port can run code on the workers (dask's docs)."""
    for name, service in compose_services().items():
        for port in service.get("ports", []):
            assert str(port).startswith("127.0.0.1:"), (name, port)
    assert "ports" not in compose_services()["scheduler"] or all(
        not str(p).endswith(":8786") for p in compose_services()["scheduler"]["ports"])
    dockerfile = (ROOT / "Dockerfile").read_text()
    assert "WORKDIR /data" in dockerfile and "COPY configs ./configs" in dockerfile
