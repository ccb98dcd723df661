"""The ``btf`` command line: one subcommand per stage, plus ``btf run CONFIG``."""

from __future__ import annotations

import argparse
import dataclasses
import os
import sys
from functools import cache, partial
from pathlib import Path

from pipeline import __version__
from pipeline.errors import BTFError
from pipeline.params import ParamError, add_arguments, from_namespace
from pipeline.session import LOCAL_SCHEDULERS, TLS, RuntimeOptions, Session, check_scheduler
from pipeline.stage import Stage
from pipeline.stages import stage as find_stage

EPILOG = """\
examples:
  btf generate out/wood.zarr --material wood --size 512 --sampling abtf:24,8
  btf inspect out/wood.zarr --scan
  btf preview out/wood.zarr out/wood.png
  btf export out/wood.zarr out/layers --light 0,8,16 --format exr
  btf ingest out/layers out/again.zarr
  btf run configs/demo.yaml --scheduler tcp://127.0.0.1:8786

'btf COMMAND --help' explains each command's options."""


class _Formatter(argparse.RawDescriptionHelpFormatter):
    def __init__(self, prog):
        super().__init__(prog, max_help_position=32)


def _scheduler(text: str) -> str:
    try:
        return check_scheduler(text)
    except ValueError as exc:
        raise argparse.ArgumentTypeError(str(exc)) from None


def _bytes(text: str) -> int:
    from dask.utils import parse_bytes

    try:
        value = parse_bytes(text)
    except (ValueError, TypeError):
        raise argparse.ArgumentTypeError(f"expected a size such as 8GiB or 500MB, got "
                                         f"{text!r}") from None
    if value <= 0:
        raise argparse.ArgumentTypeError(f"must be positive, got {text!r}")
    return value


def _positive(text: str) -> int:
    try:
        value = int(text)
    except ValueError:
        value = 0
    if value < 1:
        raise argparse.ArgumentTypeError(f"expected a positive integer, got {text!r}")
    return value


def _runtime_parser() -> argparse.ArgumentParser:
    parent = argparse.ArgumentParser(add_help=False)
    group = parent.add_argument_group("scheduling")
    group.add_argument(
        "--scheduler", type=_scheduler, default=None, metavar="NAME",
        help=f"where to compute: {', '.join(LOCAL_SCHEDULERS)} (dask's local schedulers), "
             "tcp://HOST:PORT of a running dask scheduler, or tls://HOST:PORT of one that "
             "only admits clients with certificates (default: threads)")
    group.add_argument("--tls-ca-file", metavar="PEM", default=None,
                       help="CA certificate a tls:// scheduler's certificate must be signed by "
                            "(default: dask config distributed.comm.tls.ca-file)")
    group.add_argument("--tls-cert", metavar="PEM", default=None,
                       help="this client's certificate, signed by the same CA (default: dask "
                            "config distributed.comm.tls.client.cert)")
    group.add_argument("--tls-key", metavar="PEM", default=None,
                       help="this client's private key, if not in --tls-cert (default: dask "
                            "config distributed.comm.tls.client.key)")
    group.add_argument("--workers", type=_positive, default=None, metavar="N",
                       help="local worker threads or processes (default: one per core)")
    group.add_argument("-q", "--quiet", action="store_true",
                       help="no progress bars or progress messages")
    return parent


def _options(args: argparse.Namespace) -> RuntimeOptions:
    return RuntimeOptions(scheduler=args.scheduler or "threads", workers=args.workers,
                          quiet=args.quiet, tls=TLS(args.tls_ca_file, args.tls_cert,
                                                    args.tls_key))


def _run_stage(stage: Stage, parser: argparse.ArgumentParser, args: argparse.Namespace) -> int:
    try:
        params = from_namespace(stage.params, args)
    except ParamError as exc:
        flag = exc.name.upper() if exc.name in _positionals(stage) else "--" + exc.name.replace(
            "_", "-")
        parser.error(f"{flag}: {exc.message}")
    with Session(_options(args)) as session:
        stage.run(params, session)
    return 0


def _positionals(stage: Stage) -> set[str]:
    return {f.name for f in dataclasses.fields(stage.params) if f.metadata.get("positional")}


def _run_config(args: argparse.Namespace) -> int:
    from pipeline.config import execute, load, runtime_for, scene_lines
    from pipeline.provenance import command_line

    plan = load(args.config, tuple(args.set))
    given = {name for name in ("scheduler", "workers") if getattr(args, name) is not None}
    options = runtime_for(plan, _options(args), given)
    if args.check:
        print(f"{plan.path}: valid; {len(plan.stages)} stage(s) on {options.scheduler}:")
        for step in plan.stages:
            print("  " + command_line(step.name, step.params))
        for line in scene_lines(plan):
            print(line)
        return 0
    with Session(options) as session:
        _check_plan(plan, options, session, args)
        if args.plan:
            return 0
        execute(plan, session)
    return 0


def _check_plan(plan, options, session, args) -> None:
    """Estimate every stage; print it with ``--plan``; refuse what cannot fit in memory."""
    import psutil

    from pipeline import planning

    plans = planning.plan_stages(plan.stages)
    if args.memory_limit is not None:
        limit, threads, source = args.memory_limit, args.worker_threads, "--memory-limit"
    else:
        limit, threads, source = planning.worker_limit(options, session.client)
    if args.plan:
        cores = (sum(w.get("nthreads", 1) for w in session.client.scheduler_info()[
            "workers"].values()) if session.client is not None else os.cpu_count() or 1)
        print(f"{plan.path}: plan of {len(plan.stages)} stage(s) on {options.scheduler}\n")
        print(planning.report(plans, cores=cores, limit=limit, threads=threads,
                              source=source))
    planning.check_memory(plans, limit, threads, source, psutil.virtual_memory().available)


def build_parser(only: Stage | None = None) -> argparse.ArgumentParser:
    """The argument parser of ``btf`` with every subcommand, or with stage ``only`` alone.

    ``only`` spares a stage's command the imports of every other stage (0.3-0.5 s).
    """
    parser = argparse.ArgumentParser(
        prog="btf", formatter_class=_Formatter, epilog=EPILOG,
        description="A dataflow pipeline for measured BTFs (bidirectional texture functions) "
                    "kept as chunked zarr stores, computed with dask on a laptop or a cluster.")
    parser.add_argument("--version", action="version", version=f"btf {__version__}")
    sub = parser.add_subparsers(dest="command", metavar="COMMAND", required=True)
    runtime = _runtime_parser()
    if only is None:
        from pipeline.stages import STAGES

        chosen = list(STAGES.values())
    else:
        chosen = [only]
    for stage in chosen:
        p = sub.add_parser(stage.name, parents=[runtime], help=stage.summary,
                           description=stage.description, formatter_class=_Formatter)
        add_arguments(p, stage.params)
        p.set_defaults(handler=partial(_run_stage, stage, p))
    if only is not None:
        return parser
    run = sub.add_parser(
        "run", parents=[runtime], formatter_class=_Formatter,
        help="run the stages of a YAML config in order",
        description="Run the stages listed in a YAML config, after validating all of it "
                    "(unknown keys, wrong types, missing inputs are reported with their line). "
                    "Stages whose output store is already up to date are skipped. See "
                    "configs/demo.yaml.")
    run.add_argument("config", help="YAML run config")
    run.add_argument("--set", action="append", default=[], metavar="STAGE.KEY=VALUE",
                     help="override a parameter of every stage of that name, e.g. "
                          "generate.size=64 (repeatable)")
    run.add_argument("--check", action="store_true",
                     help="validate the config and print its commands without running them; "
                          "with a scene: section, what each stage computes for the scene "
                          "(blocks out of all, where its input exists already)")
    run.add_argument("--plan", action="store_true",
                     help="print, per stage, the bytes read and written, tasks, passes, peak "
                          "memory per task and on the client, and an estimated time (from "
                          "rates btf bench measured here), without running anything; refuse "
                          "(exit 1) a plan that does not fit the workers' memory (checked "
                          "before every run too)")
    run.add_argument("--memory-limit", type=_bytes, default=None, metavar="SIZE",
                     help="memory per worker to plan for, e.g. 4GiB (default: the cluster's "
                          "workers' limit, or this machine's memory)")
    run.add_argument("--worker-threads", type=_positive, default=2, metavar="N",
                     help="tasks a worker runs at once, with --memory-limit (default: 2, as "
                          "docker-compose.yml's workers)")
    run.set_defaults(handler=_run_config)
    _add_plugins(sub)
    return parser


PLUGINS = "btf.commands"  # entry point group of commands other packages add (btf bench)


@cache
def _plugins() -> dict:
    """Commands added through entry points, by name (not imported until one runs).

    Read once a process: scanning the installed packages' metadata takes 4 ms, at every
    :func:`main` (10 s of CPU over a ``make test``, which calls it in-process).
    """
    from importlib.metadata import entry_points

    return {ep.name: ep for ep in entry_points(group=PLUGINS)}


def _summary(module: str) -> str:
    """The first line of a module's docstring, read from its source without importing it."""
    import ast
    from importlib.util import find_spec

    spec = find_spec(module)
    if spec is None or spec.origin is None:
        return ""
    doc = ast.get_docstring(ast.parse(Path(spec.origin).read_text())) or ""
    line = doc.splitlines()[0].rstrip(".") if doc else ""
    return line[:1].lower() + line[1:]


def _add_plugins(sub) -> None:
    for name, ep in sorted(_plugins().items()):
        sub.add_parser(name, add_help=False, help=_summary(ep.module))


def main(argv: list[str] | None = None) -> int:
    """Entry point of the ``btf`` console script; returns the exit status.

    Also for ``--help`` (0) and usage errors (2), which argparse ends with ``SystemExit``: a
    caller running ``main`` in-process gets the status back like any other.
    """
    argv = sys.argv[1:] if argv is None else list(argv)
    plugin = _plugins().get(argv[0]) if argv else None
    command = argv[0] if argv else ""
    try:
        if plugin is not None:  # a command with its own parser, options and help
            handler = partial(plugin.load(), argv[1:])
        else:
            named = find_stage(command) if command and not command.startswith("-") else None
            args = build_parser(only=named).parse_args(argv)
            command, handler = args.command, partial(args.handler, args)
        return handler()
    except SystemExit as exc:
        return _status(exc)
    except BTFError as exc:
        print(f"btf {command}: error: {exc}", file=sys.stderr)
        return 1
    except KeyboardInterrupt:
        print(f"btf {command}: interrupted", file=sys.stderr)
        return 130
    except BrokenPipeError:  # output piped into a program that stopped reading (e.g. head)
        sys.stderr.close()
        return 0
    except Exception as exc:  # object storage failing inside zarr's chunk I/O: one message
        from pipeline.storage import explain_request

        named = explain_request(exc)
        if named is None:
            raise
        print(f"btf {command}: error: {named}", file=sys.stderr)
        return 1


def _status(exc: SystemExit) -> int:
    """The exit status ``sys.exit`` would give (a message is printed, as it would print it)."""
    if exc.code is None or isinstance(exc.code, int):
        return exc.code or 0
    print(exc.code, file=sys.stderr)
    return 1


def console() -> int:
    """The ``btf`` console script: :func:`main`, then a quick exit.

    At exit the interpreter tears down its 2,000 modules with a full garbage collection after
    each step, over the 230,000 objects that dask, zarr, xarray, scipy and numba leave: 0.5-0.8 s
    after a stage's work was done, at the end of every command and before every rerun of a
    run after a fault. Frozen (``gc.freeze``), those objects are left to the process's end:
    what is freed by reference counts still is (stdout, stderr, files no cycle holds), but
    finalizers of objects in reference cycles no longer run at exit, which Python never
    promised; btf closes what it writes before it returns. Not in :func:`main`, which tests
    call in their own process, where frozen objects would stay until it ends.
    """
    import gc

    status = main()
    gc.freeze()
    return status


if __name__ == "__main__":
    sys.exit(console())
