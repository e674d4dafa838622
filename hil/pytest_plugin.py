"""The pytest plugin: test a TCU on the HIL bench with pytest (the ``pytest11`` entry point ``hil.pytest_plugin``;
in a tree not installed, ``pytest -p hil.pytest_plugin``).

    def test_identifies_after_the_fault(hil_run):
        run = hil_run("scenarios/ffcc_a.toml", set={"run.duration_s": 1.0})
        require(run, limit("t_identified_s", hi=0.7, req="REQ-ID-1"),
                in_range("TcuStatus.MuHat", 0.0, 0.35, during=("fault", 0.0, 0.3), valid="TcuStatus.ObserverValid"))

Options: ``--hil-bus`` (default auto, as ``hil run``), ``--hil-mode lockstep|realtime``, ``--hil-tcu
builtin|external``, ``--hil-tcu-cmd CMD`` (with ``external``: the TCU under test, started before each run
and stopped after; ``{scenario}``, ``{bus}``, ``{mode}`` in CMD are filled in), ``--hil-out DIR`` (logs and
figures; default a directory under pytest's temporary base).

``hil_run(scenario, set=None, seed=None, strategy=None, reality=None, control=None)`` runs once per whole specification
(those and the bus, mode and TCU) within the session and returns a ``hil.checks.Run``.  Files named
``test_*.toml`` with ``[[check]]`` tables and a ``scenario`` (``hil.checks.spec``) are collected as tests,
one per check.

Outcomes (``hil.checks.outcome``): a failed check, a TCU that fell silent or came late *fail*; a bench
that could not judge (``hil.errors.BenchError``) is reported as an *error* (JUnit ``<error>``; this
plugin marks the report as pytest marks a broken fixture's); a bus not available here *skips*, and is
an error under ``CI=true``.  A failure's output holds one line per failed check, ``[[ATTACHMENT|png]]``
lines (a figure per failed check), the log, the recording, the command that repeats the test (``reproduce:``,
its node id with every ``--hil-*`` option) and the one that judges its log again (``re-judge: hil check``,
checks written in Python exported beside the log); the checks of ``test_*.toml`` files are judged by the
judge ``hil check`` uses (``hil.checks.judge.judged``), a run the TCU's failure ended included;
the plugin sets ``junit_logging = system-out`` (unless the project sets another value than ``no``) so
that the JUnit XML keeps them.  Suite properties (``--junitxml``): the package version, the TCU under test,
the bus and mode, and for each DBC the session's runs spoke (the scenario's ``[bus] dbc`` or ``hil/hil.dbc``)
its file name (``dbc``) and digest (``dbc_sha256``), a pair per DBC in the order the runs first used them.

This module imports only pytest and the standard library when it loads: a pytest session that never
asks for a HIL run pays nothing for it.
"""
from __future__ import annotations

import os
import shlex
import subprocess
from pathlib import Path

import pytest

_BENCH = pytest.StashKey()
_RUNS = pytest.StashKey()


def pytest_addoption(parser):
    group = parser.getgroup("hil", "railway-hil: test a TCU on the HIL bench")
    group.addoption("--hil-bus", default="auto", help="bus between plant and TCU (as hil run --bus; default auto; "
                    "inprocess: the built-in TCU in the same process)")
    group.addoption("--hil-mode", default="lockstep", choices=("lockstep", "realtime"), help="lockstep (default) or "
                    "realtime")
    group.addoption("--hil-tcu", default="builtin", choices=("builtin", "external"), help="builtin: the project's "
                    "TCU (default); external: the TCU under test, already on the bus or started by --hil-tcu-cmd")
    group.addoption("--hil-tcu-cmd", default=None, metavar="CMD", help="command that starts the TCU under test "
                    "for each run ({scenario}, {handover}, {bus}, {mode} filled in); stopped after the run")
    group.addoption("--hil-out", default=None, metavar="DIR", help="directory for the runs' logs and the failures' "
                    "figures (default: under pytest's temporary base)")


@pytest.hookimpl(trylast=True)
def pytest_configure(config):
    config.stash[_BENCH] = Bench(config)
    # the failures' lines, attachments and logs are written to the test's output: keep it in the JUnit XML.
    # pytest reads junit_logging before any plugin loads, so the --junitxml writer is set after it is made
    xml = _junit_writer(config)
    if xml is not None and getattr(xml, "logging", None) == "no":
        xml.logging = "system-out"


def _junit_writer(config):
    """pytest's --junitxml writer (LogXML), None without --junitxml.  Its stash key is pytest's own: where
    it is gone, the output stays out of the XML (the terminal has it) and the suite has no properties."""
    try:
        from _pytest.junitxml import xml_key
    except ImportError:  # pytest moved its junitxml key: no XML properties (docstring)
        return None
    return config.stash.get(xml_key, None)


class Bench:
    """The session's runs: options, output directory, and the cache of runs by their whole specification
    (a run, or the exception it ended with, is kept and given again)."""

    def __init__(self, config):
        opt = config.option
        self.config = config
        self.bus, self.mode, self.tcu, self.tcu_cmd = opt.hil_bus, opt.hil_mode, opt.hil_tcu, opt.hil_tcu_cmd
        self.out_opt = opt.hil_out
        self.cache: dict = {}
        self.skipped: list[str] = []    # why runs were skipped (the bus left to auto was not available)
        self.dbcs: dict = {}           # DBC path -> (file name, SHA-256 of its text) of the runs asked for
        self._out = None

    @property
    def out(self) -> Path:
        if self._out is None:
            if self.out_opt:
                self._out = Path(self.out_opt).resolve()
                self._out.mkdir(parents=True, exist_ok=True)
            else:
                self._out = self.config._tmp_path_factory.mktemp("hil", numbered=True)
        return self._out

    def run(self, scenario, set=None, seed=None, strategy=None, reality=None, control=None):
        """The run of this specification (once per session); raises what it ended with (the same verdict
        for every test that asks, its traceback started anew each time: it never grows).  ``control``: the
        TCU's control law (``--set control.law=...``)."""
        __tracebackhide__ = True
        overrides = dict(set or {})
        if control is not None:
            overrides["control.law"] = control
        reality = tuple(reality or ())
        key = (str(Path(scenario).resolve()), tuple(sorted((k, repr(v)) for k, v in overrides.items())), seed,
               strategy, reality, self.bus, self.mode, self.tcu, self.tcu_cmd)
        if key not in self.cache:
            try:
                self.cache[key] = ("ok", self._run(scenario, overrides, seed, strategy, reality))
            except pytest.skip.Exception as e:
                self.cache[key] = ("raise", e)
            except BaseException as e:  # noqa: BLE001 - kept, raised again for the same specification
                if isinstance(e, (KeyboardInterrupt, SystemExit)):
                    raise
                self.cache[key] = ("raise", e)
        how, value = self.cache[key]
        if how == "raise":
            raise value.with_traceback(None)
        return value

    def command(self, scenario, overrides, seed, strategy, reality) -> str:
        """The ``hil run`` command line that repeats this run."""
        parts = ["hil", "run", str(scenario), "--bus", self.bus, "--mode", self.mode]
        parts += ["--seed", str(seed)] if seed is not None else []
        # the strategy is the built-in TCU's: an external TCU identifies (or not) as it does
        parts += ["--strategy", strategy] if strategy and self.tcu != "external" else []
        for k, v in overrides.items():
            parts += ["--set", f"{k}={_toml_value(v)}"]
        for r in reality:
            parts += ["--reality", r]
        parts += ["--tcu", "external"] if self.tcu == "external" else []
        return shlex.join(parts)

    def _run(self, scenario, overrides, seed, strategy, reality):
        __tracebackhide__ = True
        import hil
        from hil.checks import Run
        from hil.checks.outcome import deadlines, run_error
        from hil.errors import BenchError, BusError

        sc = hil.load_scenario(scenario, overrides)
        self._speaks(sc)
        if reality:
            from hil.effects import parse_effect, with_reality
            sc = with_reality(sc, dict(parse_effect(r) for r in reality))
        from identifier import DEFAULT_STRATEGY, STRATEGIES
        from hil.errors import ConfigError

        strategy = strategy or DEFAULT_STRATEGY
        if strategy not in STRATEGIES:
            raise ConfigError(f"hil_run: unknown strategy {strategy!r}; available: {', '.join(sorted(STRATEGIES))}")
        external = self.tcu == "external"
        if external and self.tcu_cmd:
            from hil.bus.link import resolve
            if resolve(self.bus) in ("local", "inprocess", "hub", "udp_multicast"):
                raise BenchError(f"--hil-tcu-cmd with --hil-bus {self.bus}: that bus is opened anew by each run, so "
                                  "the TCU under test cannot join it; give one both sides open: localbus:DIR (a "
                                  "directory of your own, mode 700), udp_multicast:GROUP:PORT (python-can alone), "
                                  "socketcan:vcan0 or a python-can adapter")
        if not external:
            from hil.progress import compile_kernels
            compile_kernels("hil_run")
        command = self.command(scenario, overrides, seed, strategy, reality)
        out = self.out / f"run{len(self.cache) + 1:03d}"        # a directory per run: logs are named by
        child = None                                               # scenario, strategy, seed
        try:
            child = self._start_tcu(scenario, sc, out) if external and self.tcu_cmd else None
            summary = hil.run(sc, strategy, seed, bus=self.bus, mode=self.mode, external_tcu=external, out_dir=out,
                              progress=False, tcu_process=child)
        except BusError as e:
            reason = f"bus not available: {e}"
            if self.bus != "auto":
                raise BenchError(f"--hil-bus {self.bus}: {e} (a bus named explicitly must open; leave it to auto "
                                 "to skip where no bus is available)") from None
            if os.environ.get("CI") == "true":
                raise BenchError(f"{reason} (CI=true: a missing bus is an error, not a skip)") from None
            self.skipped.append(reason)
            pytest.skip(reason)
        except Exception as e:  # noqa: BLE001 - every run error is a fail or an error (hil.checks.outcome)
            verdict = run_error(e)
            verdict.command = command
            verdict.log = (getattr(e, "summary", None) or {}).get("mcap")
            raise verdict from None          # the verdict says what happened; the run's own frames are noise
        finally:
            if child is not None:
                _stop(child)
        run = Run.open(summary["mcap"], summary, command=command)
        verdict = deadlines(summary)
        if verdict is not None:
            verdict.command, verdict.log = command, run.path
            raise verdict
        return run

    def _speaks(self, sc) -> None:
        """Keep the digest of the DBC this run speaks: the SHA-256 of its text, as the log keeps it (what
        ``hil check`` hashes)."""
        import hashlib

        from hil.bus.mapping import scenario_dbc

        path = scenario_dbc(sc)
        if str(path) not in self.dbcs:
            self.dbcs[str(path)] = (path.name, hashlib.sha256(path.read_text().encode()).hexdigest())

    def _start_tcu(self, scenario, sc, out: Path):
        """The TCU under test started for a run (``sc``: the resolved scenario, whose hand-over fills in
        ``{handover}``), its stderr to ``out/tcu.stderr`` (quoted when it dies); a command that ends at once
        (a typo, a missing module) is ``TcuDidNotStart`` here, and one that ends later before it joins is
        found by the run's watch (``hil.run``'s ``tcu_process``)."""
        __tracebackhide__ = True
        import json

        from hil.errors import TcuDidNotStart
        from hil.plant_node import describe_exit, stderr_tail

        out.mkdir(parents=True, exist_ok=True)
        handover = out / "scenario.json"
        handover.write_text(json.dumps(sc.handover()))
        cmd = self.tcu_cmd.format(scenario=shlex.quote(str(scenario)), bus=shlex.quote(self.bus), mode=self.mode,
                                  handover=shlex.quote(str(handover)))
        stderr_path = out / "tcu.stderr"
        with open(stderr_path, "wb") as err:
            child = subprocess.Popen(cmd, shell=True, start_new_session=True, stdin=subprocess.DEVNULL, stderr=err)
        child.stderr_path = str(stderr_path)
        try:
            child.wait(0.2)             # let it open the bus; the plant waits [bus] startup_timeout_s for it
        except subprocess.TimeoutExpired:  # still running after 0.2 s: it started
            return child
        raise TcuDidNotStart(f"--hil-tcu-cmd {cmd!r}: the TCU process {describe_exit(child)} before it joined "
                             f"the bus{stderr_tail(child)}")


def _stop(child, timeout_s: float = 5.0) -> None:
    """Stop the TCU under test started for a run: SIGTERM to its process group, SIGKILL after ``timeout_s``."""
    import signal

    if child.poll() is None:
        try:
            os.killpg(child.pid, signal.SIGTERM)
            child.wait(timeout_s)
        except subprocess.TimeoutExpired:  # a TCU that ignores SIGTERM is killed
            os.killpg(child.pid, signal.SIGKILL)
            child.wait()
        except ProcessLookupError:  # the group has ended already
            pass


def _toml_value(v) -> str:
    if isinstance(v, bool):
        return "true" if v else "false"
    if isinstance(v, str):
        return f'"{v}"'
    return repr(v)


@pytest.fixture
def hil_run(request):
    """``hil_run(scenario, set=None, seed=None, strategy=None, reality=None, control=None)``: the run of that specification
    on the session's bench (once per session), a ``hil.checks.Run``: ``.summary``, ``.path`` (the log),
    ``.signal(name)``, ``.command`` (the ``hil run`` line that repeats it)."""
    bench = request.config.stash[_BENCH]

    def run(scenario, set=None, seed=None, strategy=None, reality=None, control=None):
        __tracebackhide__ = True
        runs = request.node.stash.setdefault(_RUNS, [])
        try:
            result = bench.run(scenario, set, seed, strategy, reality, control)
        except Exception as e:
            runs.append(e)
            raise
        runs.append(result)
        return result

    return run


def pytest_collection_finish(session):
    """The suite's properties in the JUnit XML, when a test of the session runs the bench: the package
    version, the TCU under test, the bus and mode (the DBCs come at the session's end, from its runs)."""
    xml = _junit_writer(session.config)
    if xml is None or not any(isinstance(i, CheckItem) or "hil_run" in getattr(i, "fixturenames", ())
                              for i in session.items):
        return
    from importlib.metadata import PackageNotFoundError, version

    bench = session.config.stash[_BENCH]
    try:
        package = version("railway-hil")
    except PackageNotFoundError:  # a source tree, not installed: said so in the report
        package = "unknown (not installed)"
    if bench.tcu == "external":
        # the session's bus and mode filled in; {scenario} and {handover} stay: they change from run to run
        cmd = (bench.tcu_cmd or "").replace("{bus}", shlex.quote(bench.bus)).replace("{mode}", bench.mode)
        tcu = f"external: {cmd}" if bench.tcu_cmd else "external (already on the bus)"
    else:
        tcu = "builtin (hil.tcu_node)"
    for name, value in (("railway_hil_version", package), ("tcu_under_test", tcu), ("bus", f"{bench.bus} {bench.mode}")):
        xml.add_global_property(name, value)


@pytest.hookimpl(tryfirst=True)
def pytest_sessionfinish(session):
    """The DBCs the session's runs spoke, as suite properties: for each, ``dbc`` (its file name) and
    ``dbc_sha256`` (the SHA-256 of its text, as each log keeps it and ``hil check`` hashes), in the order
    the runs first used them; before pytest's JUnit writer writes the file (tryfirst)."""
    xml = _junit_writer(session.config)
    bench = session.config.stash.get(_BENCH, None)
    if xml is None or bench is None:
        return
    for name, digest in bench.dbcs.values():
        xml.add_global_property("dbc", name)
        xml.add_global_property("dbc_sha256", digest)


def pytest_terminal_summary(terminalreporter):
    """Why HIL runs were skipped (the bus left to ``auto`` was not available here), once, at the end."""
    bench = terminalreporter.config.stash.get(_BENCH, None)
    if bench is None or not bench.skipped:
        return
    reasons = list(dict.fromkeys(bench.skipped))
    terminalreporter.write_line(f"hil: {len(bench.skipped)} run(s) skipped: {reasons[0]}"
                                + (f" (and {len(reasons) - 1} other reason(s))" if len(reasons) > 1 else ""),
                                yellow=True)


# -- test files as data ---------------------------------------------------------------------------------
def pytest_collect_file(file_path, parent):
    if file_path.suffix == ".toml" and file_path.name.startswith("test_"):
        return ChecksFile.from_parent(parent, path=file_path)
    return None


class ChecksFile(pytest.File):
    """A ``test_*.toml`` file: one test per ``[[check]]``, all over one run of its scenario."""

    def collect(self):
        from hil.checks.spec import load_checks
        from hil.errors import ConfigError

        suite = load_checks(self.path)
        if suite.scenario is None:
            raise ConfigError(f"{self.path}: no scenario = \"...\" (the scenario file its checks judge a run of)")
        for i, check in enumerate(suite.checks, start=1):
            yield CheckItem.from_parent(self, name=f"{i}-{check.name}", suite=suite, check=check)

    def repr_failure(self, excinfo):
        from hil.errors import HilError

        if isinstance(excinfo.value, HilError):
            return str(excinfo.value)          # one line naming the file and the field
        return super().repr_failure(excinfo)


def _failed_run(error):
    """(the log of a run whose TCU failed it, opened once and kept on the error; its verdict) or (None,
    None): a ``TcuFailed`` with a log is judged check by check as ``hil check`` judges that log."""
    from hil.checks import Run
    from hil.checks.outcome import TcuFailed, recorded
    from hil.errors import HilError

    log = getattr(error, "log", None)
    if not isinstance(error, TcuFailed) or not log:
        return None, None
    run = getattr(error, "hil_log_run", None)
    if run is None:
        try:
            run = Run.open(log)
            error.hil_log_run = run
        except (HilError, OSError):  # no readable log: the error is reported without its figures
            return None, None
    try:
        return run, recorded(run) or error
    except HilError:  # the log is unreadable: the error is reported without the log's figures
        return None, None


def _judge_one(check, run, verdict):
    """One check of a checks file, by the judge ``hil check`` and ``require`` use (``judge.judged``)."""
    from hil.checks.judge import judged

    return judged([check], run, verdict)[0]


class CheckItem(pytest.Item):
    def __init__(self, *, suite, check, **kw):
        super().__init__(**kw)
        self.suite, self.check = suite, check

    def runtest(self):
        from hil.checks import CheckFailed

        bench = self.config.stash[_BENCH]
        runs = self.stash.setdefault(_RUNS, [])
        try:
            run = bench.run(self.suite.scenario, self.suite.set, self.suite.seed, self.suite.strategy)
        except Exception as e:
            runs.append(e)
            run, verdict = _failed_run(e)
            if run is None:
                raise
        else:
            runs.append(run)
            verdict = None
        result = _judge_one(self.check, run, verdict)
        if not result.passed:
            raise CheckFailed([result], run, (self.check,), verdict)

    def repr_failure(self, excinfo):
        from hil.checks import CheckFailed
        from hil.checks.outcome import TcuFailed
        from hil.errors import HilError

        if isinstance(excinfo.value, (CheckFailed, TcuFailed, HilError)):
            return str(excinfo.value)
        return super().repr_failure(excinfo)

    def reportinfo(self):
        return self.path, None, f"{self.path.name}::{self.name}"


# -- what a failure shows, and errors apart from failures -------------------------------------------------
@pytest.hookimpl(wrapper=True)
def pytest_runtest_makereport(item, call):
    if call.excinfo is not None and call.when == "call" and (
            _RUNS in item.stash or type(call.excinfo.value).__name__ == "CheckFailed"):
        lines = _failure_output(item, call.excinfo.value)
        if lines:
            item.add_report_section("call", "stdout", "\n".join(lines) + "\n")
    report = yield
    if call.excinfo is not None and call.when == "call" and report.failed:
        from hil.errors import BenchError

        if isinstance(call.excinfo.value, BenchError):
            report.when = "setup"          # the bench could not judge: an error, as a broken fixture's
    return report


def _failure_output(item, error) -> list[str]:
    """One line per failed check, their figures as attachments, the runs' logs, recordings and commands."""
    from hil.checks import CheckFailed
    from hil.checks.report import attachment, figure

    lines = []
    bench = item.config.stash[_BENCH]
    if isinstance(error, CheckFailed):
        stem = item.name
        for r in error.results:
            if r.passed:
                continue
            lines.append(f"FAIL {r.line()}")
            try:
                png = figure(r, bench.out / "figures", stem)
            except Exception as e:  # noqa: BLE001 - the verdict stands without its figure
                lines.append(f"  (no figure: {type(e).__name__}: {e})")
                png = None
            if png is not None:
                lines.append(attachment(png))
    runs = list(item.stash.get(_RUNS, []))
    if isinstance(error, CheckFailed) and error.run is not None and error.run not in runs:
        runs.append(error.run)              # require() over a log's path, no hil_run
    logs = []
    for run in runs:
        log = getattr(run, "path", None) or getattr(run, "log", None)
        if log:
            logs.append(str(log))
            lines.append(f"log: {log}")
            rrd = _recording(log)
            if rrd:
                lines.append(f"recording: {rrd}")
    lines.append(f"reproduce: {_reproduce_command(item, bench)}")
    lines += _rejudge_lines(item, error, logs)
    return list(dict.fromkeys(lines))


def _reproduce_command(item, bench) -> str:
    """The command that runs this test again as it ran: pytest on its node id (the file's absolute path,
    so from any directory) with the session's ``-p`` plugins and every ``--hil-*`` option but the output
    directory (the scenario, its overrides, the seed and the strategy are the test's own)."""
    args = list(item.config.invocation_params.args)
    plugins = []
    for i, a in enumerate(args):
        if a == "-p" and i + 1 < len(args):
            plugins += ["-p", str(args[i + 1])]
        elif a.startswith("-p") and len(a) > 2 and not a.startswith("--"):
            plugins += ["-p", a[2:]]
    node = str(item.path) + (item.nodeid[item.nodeid.index("::"):] if "::" in item.nodeid else "")
    parts = ["pytest", node, *plugins, "--hil-bus", bench.bus, "--hil-mode", bench.mode, "--hil-tcu", bench.tcu]
    parts += ["--hil-tcu-cmd", bench.tcu_cmd] if bench.tcu_cmd else []
    return shlex.join(parts)


def _rejudge_lines(item, error, logs) -> list[str]:
    """``hil check LOG CHECKS.toml`` for each log the test's checks judged, to the same verdict (the one judge,
    ``hil.checks.judge.judged``): a checks file's test names its file; checks written in Python are written
    as a checks file beside the log (``hil.checks.spec.dump_checks``)."""
    import re

    from hil.checks import CheckFailed

    if not logs:
        return []
    if isinstance(item, CheckItem):
        toml = str(item.path)
    elif isinstance(error, CheckFailed) and error.checks:
        from hil.checks.spec import dump_checks

        name = re.sub(r"[^A-Za-z0-9_.-]+", "_", item.name)[:120]
        try:
            toml = str(dump_checks(error.checks, Path(logs[-1]).parent / f"{name}.checks.toml",
                                   comment=f"the checks of {item.nodeid}, written by the pytest plugin"))
        except Exception as e:  # noqa: BLE001 - the verdict stands without its re-judge file
            return [f"  (no checks file: {type(e).__name__}: {e})"]
    else:
        return []
    return [f"re-judge: {shlex.join(['hil', 'check', log, toml])}" for log in dict.fromkeys(logs)]


def _recording(log) -> str | None:
    """The Rerun recording beside a failed run's log (written once); None when it cannot be made."""
    rrd = Path(log).with_suffix(".rrd")
    if rrd.exists():
        return str(rrd)
    try:
        from hil.view import write_rrd
        out, _ = write_rrd(log)
        return str(out)
    except Exception:  # noqa: BLE001 - the log is there; hil view LOG makes the recording later
        return None
