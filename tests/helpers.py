"""Helpers shared by the tests (importable as ``helpers``)."""

from __future__ import annotations

from pathlib import Path

from pipeline.cli import main


def generate_store(path: Path, *args: str) -> Path:
    code = main(["generate", str(path), "--quiet", *args])
    assert code == 0
    return path


def no_partial_outputs(path: Path) -> bool:
    """Neither the output nor any hidden partial sibling of it exists."""
    stem = path.name.split(".")[0]
    leftovers = [p for p in path.parent.glob(f".{stem}*")
                 if "partial" in p.name or ".resume-" in p.name]
    return not path.exists() and not leftovers


ROOT = Path(__file__).resolve().parents[1]


def compose_command(service: str, *, values: dict[str, str] | None = None,
                    words: dict[str, str] | None = None) -> list[str]:
    """The command of a ``docker-compose.yml`` service, with some option values replaced.

    The cluster tests run these commands (the same programs, subcommands and options) with
    local hosts, ports and sizes, so the compose file cannot drift from what the tests run.
    ``values`` maps an option to its new value; ``words`` maps other words (addresses, config
    paths) to new ones. Every key must occur in the command.
    """
    import shlex

    import yaml

    spec = yaml.safe_load((ROOT / "docker-compose.yml").read_text())
    command = shlex.split(spec["services"][service]["command"])
    values, words = dict(values or {}), dict(words or {})
    missing = [k for k in values if k not in command] + [k for k in words if k not in command]
    assert not missing, f"docker-compose.yml's {service} command has no {missing}"
    out, applied = [], set()
    for i, word in enumerate(command):
        if i and command[i - 1] in values:
            out.append(values[command[i - 1]])
            applied.add(command[i - 1])
        else:
            out.append(words.get(word, word))
    assert applied == set(values), f"{service}: options without a value: {set(values) - applied}"
    return out


def compose_services() -> dict:
    """The services of ``docker-compose.yml``."""
    import yaml

    return yaml.safe_load((ROOT / "docker-compose.yml").read_text())["services"]


REPO = Path(__file__).resolve().parents[1]


def small_demo(folder: Path, size: int = 128) -> Path:
    """configs/demo.yaml scaled down to a ``size^2`` ground truth, written into ``folder``.

    The sample stays the central half and the surface twice the size; the scene spec goes
    to ``folder/configs/demo/`` where the config finds it when run from ``folder``.
    """
    text = (REPO / "configs" / "demo.yaml").read_text()
    for old, new in (("size: 256", f"size: {size}"),
                     ('"64:192,64:192"', f'"{size // 4}:{3 * size // 4},{size // 4}:'
                                         f'{3 * size // 4}"'),
                     ("size: [512, 512]", f"size: [{2 * size}, {2 * size}]")):
        assert old in text, old
        text = text.replace(old, new)
    scenes = folder / "configs" / "demo"
    scenes.mkdir(parents=True, exist_ok=True)
    (scenes / "scene.yaml").write_text((REPO / "configs" / "demo" / "scene.yaml").read_text())
    path = folder / "demo.yaml"
    path.write_text(text)
    return path
