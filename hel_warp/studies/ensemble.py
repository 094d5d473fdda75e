"""Ensembles and sweeps of a case script on Dask: seeds x parameter values, one process per run.

``hel-warp ensemble CASE.py --seeds A-B [--set NAME=V1,V2 ...] --out DIR -- [case args]`` runs, for every member
of the product of the parameter values and the seeds,

    python CASE.py <case args> --NAME V ... --seed S --out DIR/<member> --json --no-progress

as one task of a Dask cluster (a local one of single-threaded workers unless a scheduler is given) and one
process of its own, so no Warp state is ever shared between runs. Then it reduces the members' JSON summaries to a
mean and a standard error per metric and parameter combination (``DIR/ensemble.json`` and a printed table).

Members and folders
    A member is one (parameter values, seed); its folder ``DIR/<NAME>=<V>_..._seed<S>`` (the --set names in the
    order given; characters of a value other than letters, digits and ``.+-`` become ``_``) is the case's --out.
    After its run the folder also holds ``ensemble_member.json``: the command, exit code, status, one-line error
    and the run's JSON summary. The run's stderr is ``DIR/logs/<member>.log``. ``DIR/ensemble_command.json``
    holds the case and its arguments: a rerun with other case arguments into the same DIR is refused.

The case contract relied on
    ``--seed S``, ``--out DIR``, ``--overwrite``, ``--resume`` (continue from DIR's checkpoint; optional),
    ``--json`` (the last line of stdout is one JSON object, the summary; ``DIR/summary.json`` holds it with
    ``"status": "complete"`` once the run finished), ``--no-progress``; exit 0 ok, 1 a failed physical check
    (the summary is still printed), 2 bad input with one line ``...: error: ...`` on stderr. The options the case
    has are read once from its ``--help``; --json and --no-progress are passed only when it has them.

Resuming (the same command, rerun)
    A member is finished when its record says it exited 0 with a summary (``ok``) or 1 with a summary (``check
    failed``: the run ended, a physical check of the case did not pass; rerunning the same seed gives the same),
    or, without a record (the driver died between the run's end and its record), when ``summary.json`` says
    ``"status": "complete"`` (``check failed`` when it lists ``check_errors``). Finished members are skipped. Every
    other member runs again: with ``--resume`` when its folder holds ``checkpoint.npz`` (or ``checkpoint.prev.npz``)
    and the case has --resume, else with ``--overwrite`` (a case without --resume starts afresh).

Metrics of a member
    Every numeric leaf of its summary (int or float, not bool; finite), nested keys joined by ``.``; a list of at
    most ``MAX_LIST`` items element by element as ``name[k]``, longer lists (time series) are skipped; so are the
    measurements of the machine rather than the flow (a key matching ``TIMING``, e.g. ``wall_clock_s``,
    ``kernel_load_s``) and the top-level ``seed``. Members that are not ``ok`` do not enter the statistics.

Statistics, per parameter combination and metric, over the n members that report it
    mean          x_bar = (1/n) sum_i x_i
    jackknife     theta_(i) = (n x_bar - x_i) / (n - 1), the mean without member i;
                  SE = sqrt((n - 1)/n * sum_i (theta_(i) - theta_(.))^2), theta_(.) = (1/n) sum_i theta_(i).
                  For the mean this is exactly the standard error of the mean s / sqrt(n),
                  s^2 = sum_i (x_i - x_bar)^2 / (n - 1), since theta_(i) - x_bar = (x_bar - x_i) / (n - 1);
                  None for n < 2.
    vs reference  another ensemble's DIR: d = x_bar - x_bar_ref, SE_d = sqrt(SE^2 + SE_ref^2) (independent seeds).
                  A difference within ~2 SE_d is not resolved by the two ensembles.

Pooled metrics
    A case module that defines ``pooled_metrics(member_dirs, reference_dirs) -> dict`` is called once per
    combination with the folders of its ok members (and of the matching reference combination's, or None): figures
    that pool the members' snapshots rather than average their summaries (e.g. the rig's per-section metrics,
    ``hel_warp.studies.rig_ensemble``). Its dict lands in ``ensemble.json`` under ``pooled``; the table shows the numeric
    leaves of its ``metrics`` entry (of the whole dict without one) with the errors of its ``stderr`` entry (a
    flat dict of the same names), if any.
"""

from __future__ import annotations

import dataclasses
import itertools
import json
import math
import os
import re
import shlex
import shutil
import signal
import socket
import subprocess
import sys
import threading
import time
from pathlib import Path

from hel_warp.errors import ConfigError, HelWarpError

ENSEMBLE_JSON = "ensemble.json"
COMMAND_JSON = "ensemble_command.json"
MEMBER_RECORD = "ensemble_member.json"
SUMMARY_JSON = "summary.json"
LOG_DIR = "logs"
CHECKPOINTS = ("checkpoint.npz", "checkpoint.prev.npz")
MAX_LIST = 16
"""Lists of at most this many items enter the metrics element by element (per-section figures); longer ones (time
series) are left out."""
TIMING = re.compile(r"wall_clock|(^|_)wall_s$|kernel_load|^timing|elapsed|(^|_)seconds$|steps_per_second|throughput")
"""Summary keys that measure the machine (wall clock, kernel loading), not the flow: left out of the metrics, so
that an ensemble's result is the same however and wherever its members ran."""
MANAGED = ("--seed", "--out", "--json", "--overwrite", "--resume", "--no-progress")
"""Case options the ensemble sets itself."""
FINISHED = ("ok", "check failed")
SCHEDULER_TIMEOUT_S = 30
"""How long to wait for a --scheduler to answer, s."""
_NAME = re.compile(r"[A-Za-z][A-Za-z0-9_-]*")
_OPTION = re.compile(r"(?<![\w-])--[A-Za-z][\w-]*")

_LAUNCHER = (
    "import os, sys\n"
    "try:\n"
    "    import ctypes\n"
    "    ctypes.CDLL(None, use_errno=True).prctl(1, 9)\n"  # PR_SET_PDEATHSIG, SIGKILL: die with the worker
    "except Exception:\n"
    "    pass\n"
    "if os.getppid() != int(sys.argv[1]):\n"  # the worker died before prctl took effect
    "    os._exit(137)\n"
    "os.execv(sys.executable, [sys.executable] + sys.argv[2:])\n"
)
"""Starts a member so that it is killed when the process that started it dies (Linux): a driver killed with its
in-process workers leaves no member running on into a folder that the rerun hands to another."""

_LIVE: set = set()
_LIVE_LOCK = threading.Lock()
_STOPPING = threading.Event()
"""Set by the driver on an interrupt: its in-process workers start no further member and write no record for a
member they were running (its folder is then an interrupted one, resumed by the rerun)."""


# ------------------------------------------------------------------------------------------------ the plan
def parse_seeds(text: str) -> list[int]:
    """``A-B`` (inclusive), a seed, or a comma-separated list of them -> the seeds, in order, each once."""
    seeds: list[int] = []
    for part in str(text).split(","):
        m = re.fullmatch(r"\s*(\d+)\s*(?:-\s*(\d+)\s*)?", part)
        if not m:
            raise ConfigError(f"--seeds {text!r}: expected A-B (e.g. 0-31), a seed, or a comma-separated list of "
                              "them")
        a, b = int(m[1]), int(m[2]) if m[2] is not None else int(m[1])
        if b < a:
            raise ConfigError(f"--seeds {text!r}: the range {a}-{b} is empty; write the smaller seed first")
        seeds.extend(range(a, b + 1))
    repeated = sorted({s for s in seeds if seeds.count(s) > 1}) if len(seeds) < 10000 else []
    if repeated or len(set(seeds)) != len(seeds):
        raise ConfigError(f"--seeds {text!r}: seeds given twice ({repeated[:5]}); give each seed once")
    return seeds


def parse_sets(items) -> list[tuple[str, tuple[str, ...]]]:
    """``NAME=V1,V2`` items -> [(name, values)], in the order given (the case option is ``--NAME``)."""
    out: list[tuple[str, tuple[str, ...]]] = []
    for item in items or []:
        name, sep, text = str(item).partition("=")
        name = name.strip()
        if not sep or not _NAME.fullmatch(name):
            raise ConfigError(f"--set {item!r}: expected NAME=V1,V2,... with NAME a case option without its "
                              "dashes (e.g. --set dt=1e-3,1e-4)")
        values = tuple(v.strip() for v in text.split(","))
        if any(not v for v in values):
            raise ConfigError(f"--set {item!r}: an empty value; give NAME=V1,V2,...")
        if len(set(values)) != len(values):
            raise ConfigError(f"--set {item!r}: a value given twice")
        if name in (n for n, _ in out):
            raise ConfigError(f"--set {name}=... given twice; list all its values in one --set")
        out.append((name, values))
    return out


def _folder_value(value: str) -> str:
    return re.sub(r"[^A-Za-z0-9.+-]", "_", value)


@dataclasses.dataclass(frozen=True)
class Member:
    """One run of the ensemble: the values of the --set options and a seed."""

    parameters: tuple
    """((name, value), ...) in the order of the --set options."""
    seed: int

    @property
    def name(self) -> str:
        """The member's folder under the ensemble's DIR."""
        return "_".join([f"{n}={_folder_value(v)}" for n, v in self.parameters] + [f"seed{self.seed}"])

    def case_options(self) -> list[str]:
        """The case options that make this member: ``--NAME V ... --seed S``."""
        opts: list[str] = []
        for n, v in self.parameters:
            opts += [f"--{n}", v]
        return opts + ["--seed", str(self.seed)]


def plan(seeds, sets) -> list[Member]:
    """The members: every combination of the --set values (in order, the first option outermost) with every
    seed. Two members whose folder names collide (values that differ only in characters a folder name cannot
    hold) are refused."""
    combos = itertools.product(*[[(n, v) for v in values] for n, values in sets]) if sets else [()]
    members = [Member(tuple(c), int(s)) for c in combos for s in seeds]
    names: dict[str, Member] = {}
    for m in members:
        if m.name in names:
            raise ConfigError(f"members {names[m.name].parameters} and {m.parameters} share the folder name {m.name}"
                              "; give values that differ in letters, digits or .+-")
        names[m.name] = m
    return members


def case_options(case_file: Path) -> set[str]:
    """The ``--options`` the case script lists in its ``--help`` (read once, in a process of its own)."""
    try:
        proc = subprocess.run([sys.executable, str(case_file), "--help"], capture_output=True, text=True,
                              timeout=600, stdin=subprocess.DEVNULL)
    except subprocess.TimeoutExpired:
        raise ConfigError(f"{case_file} --help did not answer within 600 s") from None
    if proc.returncode != 0:
        lines = [ln for ln in (proc.stderr or proc.stdout).splitlines() if ln.strip()]
        raise ConfigError(f"{case_file} --help failed (exit {proc.returncode}): "
                          f"{lines[-1].strip() if lines else 'no output'}")
    return set(_OPTION.findall(proc.stdout))


def check_case(options: set[str], sets, case_args) -> None:
    """Refuse (ConfigError) a case without --seed / --out, a --set NAME that is not a case option, and case
    arguments holding an option the ensemble sets (--seed, --out, ..., a --set NAME)."""
    for required in ("--seed", "--out"):
        if required not in options:
            raise ConfigError(f"the case script has no {required} option (its --help lists none); an ensemble "
                              "needs a case that takes --seed and --out")
    for name, _ in sets:
        if f"--{name}" not in options:
            raise ConfigError(f"--set {name}=...: the case script has no option --{name}; its options: "
                              + " ".join(sorted(options)))
    own = set(MANAGED) | {f"--{n}" for n, _ in sets}
    for token in case_args:
        opt = token.split("=", 1)[0]
        if opt in own:
            why = "the --set values" if opt not in MANAGED else "the ensemble"
            raise ConfigError(f"case argument {token}: {opt} is set by {why}; leave it out of the case arguments")


# ------------------------------------------------------------------------------------------------ a member
def _read_json(path: Path):
    try:
        with open(path) as fh:
            return json.load(fh)
    except (OSError, ValueError):
        return None


def _write_json(path: Path, obj, indent=None) -> None:
    """Write atomically: a reader (or a rerun after a kill) sees the old file or the new one, never half."""
    tmp = path.with_name(f".{path.name}.{os.getpid()}.{threading.get_ident()}.tmp")
    with open(tmp, "w") as fh:
        json.dump(obj, fh, indent=indent)
    os.replace(tmp, path)


def member_state(folder) -> tuple[str, dict | None]:
    """(state, record) of a member folder: ``finished`` (record status ok / check failed, or no record and
    ``summary.json`` with ``"status": "complete"``), ``failed`` (a record of a failed run), ``interrupted``
    (the folder without either) or ``new`` (no folder)."""
    folder = Path(folder)
    record = _read_json(folder / MEMBER_RECORD)
    if isinstance(record, dict) and record.get("status") in FINISHED:
        return "finished", record
    if not isinstance(record, dict):
        summary = _read_json(folder / SUMMARY_JSON)
        if isinstance(summary, dict) and summary.get("status") == "complete":
            # the run ended but its record was not written (the driver died in between): ok, or check failed
            errors = summary.get("check_errors")
            failed = bool(errors) and isinstance(errors, list)
            return "finished", {"name": folder.name, "status": "check failed" if failed else "ok",
                                "returncode": None, "error": f"check failed: {errors[0]}" if failed else None,
                                "summary": summary, "source": SUMMARY_JSON}
        return ("interrupted" if folder.exists() else "new"), None
    return "failed", record


def _last_json(stdout: str):
    """The last non-empty line of stdout as a JSON object, or None."""
    for line in reversed(stdout.splitlines()):
        if line.strip():
            try:
                obj = json.loads(line)
            except ValueError:
                return None
            return obj if isinstance(obj, dict) else None
    return None


def error_line(stderr: str, returncode: int) -> str:
    """The one line that says why a member failed: the last stderr line with ``error:`` or ``check failed``,
    else the last stderr line (a traceback's exception), else the exit code or signal."""
    lines = [ln.strip() for ln in stderr.splitlines() if ln.strip()]
    for line in reversed(lines):
        if "error:" in line or "check failed" in line:
            return line
    if returncode < 0:
        try:
            name = signal.Signals(-returncode).name
        except ValueError:
            name = str(-returncode)
        return f"killed by signal {name}" + (f" (last stderr line: {lines[-1]})" if lines else "")
    if lines:
        return lines[-1]
    return f"exit code {returncode}, nothing on stderr"


def run_member(spec: dict) -> dict:
    """Run one member (on a Dask worker): skip it when finished, else run the case in a process of its own
    (``--resume`` from a checkpoint, ``--overwrite`` an interrupted folder) and write its record. Returns the
    record, with ``ran`` telling whether it ran now."""
    folder = Path(spec["dir"])
    state, record = member_state(folder)
    if state == "finished":
        return {**record, "name": spec["name"], "ran": False}
    if _STOPPING.is_set():
        return {"name": spec["name"], "status": "failed", "error": "not started: the ensemble was interrupted",
                "ran": False}
    argv = list(spec["argv"]) + ["--out", str(folder)]
    argv += [opt for opt, has in (("--json", spec["json"]), ("--no-progress", spec["no_progress"])) if has]
    mode = "new"
    if folder.exists():
        (folder / MEMBER_RECORD).unlink(missing_ok=True)
        if spec["resume"] and any((folder / c).exists() for c in CHECKPOINTS):
            argv.append("--resume")
            mode = "resume"
        elif spec["overwrite"]:
            argv.append("--overwrite")
            mode = "overwrite"
        else:
            shutil.rmtree(folder)
            mode = "overwrite"
    log = Path(spec["log"])
    log.parent.mkdir(parents=True, exist_ok=True)
    cwd = spec.get("cwd") if spec.get("cwd") and os.path.isdir(spec["cwd"]) else None
    env = {**os.environ, "PYTHONUNBUFFERED": "1"}
    start = time.perf_counter()
    with open(log, "w") as err:
        proc = subprocess.Popen([sys.executable, "-c", _LAUNCHER, str(os.getpid()), spec["case"], *argv],
                                stdout=subprocess.PIPE, stderr=err, stdin=subprocess.DEVNULL, cwd=cwd, env=env,
                                text=True, start_new_session=True)
        with _LIVE_LOCK:
            _LIVE.add(proc)
        try:
            stdout, _ = proc.communicate()
        finally:
            with _LIVE_LOCK:
                _LIVE.discard(proc)
    wall = time.perf_counter() - start
    rc = proc.returncode
    if _STOPPING.is_set():
        return {"name": spec["name"], "status": "failed", "error": "interrupted with the ensemble", "ran": True}
    summary = _last_json(stdout) if spec["json"] else None
    if summary is None and not spec["json"]:
        disk = _read_json(folder / SUMMARY_JSON)
        summary = disk if isinstance(disk, dict) else None
    if rc == 0 and (summary is not None or not spec["json"]):
        status = "ok"
    elif rc == 1 and summary is not None:
        status = "check failed"
    else:
        status = "failed"
    error = None
    if status != "ok":
        error = error_line(log.read_text(errors="replace"), rc)
        if rc == 0:
            error = "exit 0, but the last line of stdout is not a JSON object (the case's --json summary)"
    record = {"name": spec["name"], "status": status, "returncode": rc, "error": error, "mode": mode,
              "command": shlex.join(["python", spec["case"], *argv]), "wall_s": wall, "host": socket.gethostname(),
              "summary": summary}
    folder.mkdir(parents=True, exist_ok=True)
    _write_json(folder / MEMBER_RECORD, record)
    return {**record, "ran": True}


def stop_members() -> int:
    """Terminate the members this process started that still run (the driver's in-process workers, on an
    interrupt); returns how many."""
    _STOPPING.set()
    with _LIVE_LOCK:
        live = list(_LIVE)
    for proc in live:
        try:
            os.killpg(proc.pid, signal.SIGTERM)
        except OSError:
            pass
    return len(live)


# ------------------------------------------------------------------------------------------------ statistics
def scalar_metrics(obj, prefix: str = "") -> dict:
    """The metrics of a summary: numeric leaves, nested keys joined by ``.``, short lists as ``name[k]`` (module
    docstring); insertion order kept."""
    out: dict = {}
    if isinstance(obj, dict):
        for key, value in obj.items():
            key = str(key)
            if TIMING.search(key) or (not prefix and key == "seed"):
                continue
            out.update(scalar_metrics(value, f"{prefix}.{key}" if prefix else key))
    elif isinstance(obj, list):
        if len(obj) <= MAX_LIST:
            for k, value in enumerate(obj):
                out.update(scalar_metrics(value, f"{prefix}[{k}]"))
    elif isinstance(obj, bool) or obj is None:
        pass
    elif isinstance(obj, (int, float)) and math.isfinite(obj):
        out[prefix] = float(obj)
    return out


def jackknife_mean(values) -> tuple[float, float | None]:
    """(mean, jackknife standard error of the mean) of ``values``: the leave-one-out means theta_(i) and
    SE = sqrt((n - 1)/n * sum (theta_(i) - theta_(.))^2), which for the mean equals s / sqrt(n) (module
    docstring); SE None for fewer than two values."""
    import numpy as np

    x = np.asarray(values, dtype=np.float64)
    n = len(x)
    if n == 0:
        raise ValueError("no values")
    mean = float(np.mean(x))
    if n < 2:
        return mean, None
    loo = (np.sum(x) - x) / (n - 1)
    return mean, float(np.sqrt((n - 1) / n * np.sum((loo - np.mean(loo)) ** 2)))


def _statistics(summaries: list[dict]) -> dict:
    """Per metric: n, mean, stderr (jackknife) and whether it differs between members (``varies``)."""
    per_member = [scalar_metrics(s) for s in summaries]
    names: dict = {}
    for m in per_member:
        names.update(dict.fromkeys(m))
    out = {}
    for name in names:
        values = [m[name] for m in per_member if name in m]
        mean, se = jackknife_mean(values)
        out[name] = {"n": len(values), "mean": mean, "stderr": se, "varies": len(set(values)) > 1}
    return out


def _difference(stats: dict, ref: dict) -> dict:
    """Per metric both ensembles report: the difference of the means and its standard error (quadrature)."""
    out = {}
    for name, s in stats.items():
        r = ref.get(name)
        if r is None:
            continue
        se = None if s["stderr"] is None or r["stderr"] is None else math.hypot(s["stderr"], r["stderr"])
        out[name] = {"difference": s["mean"] - r["mean"], "stderr": se, "reference_mean": r["mean"],
                     "reference_n": r["n"]}
    return out


def load_reference(folder) -> tuple[Path, dict]:
    """(folder, ensemble.json) of a reference ensemble; ConfigError when it is none."""
    folder = Path(folder).resolve()
    data = _read_json(folder / ENSEMBLE_JSON)
    if not isinstance(data, dict) or "combinations" not in data:
        raise ConfigError(f"--reference {folder}: no {ENSEMBLE_JSON} there; give the DIR of a finished "
                          "hel-warp ensemble")
    return folder, data


def _match_reference(parameters: dict, reference: dict) -> dict | None:
    """The reference combination for ``parameters``: its only one, else the one with the same values."""
    combos = reference["combinations"]
    if len(combos) == 1:
        return combos[0]
    for c in combos:
        if c["parameters"] == parameters:
            return c
    return None


def _call_hook(hook, dirs: list[str], ref_dirs: list[str] | None) -> dict:
    try:
        result = hook(dirs, ref_dirs)
        json.dumps(result)
    except HelWarpError as exc:
        return {"error": str(exc)}
    except Exception as exc:  # noqa: BLE001 - the members are safe on disk; the ensemble reports and goes on
        return {"error": f"{type(exc).__name__}: {exc}"}
    if not isinstance(result, dict):
        return {"error": f"pooled_metrics returned {type(result).__name__}, not a dict"}
    return {"result": result}


def summarise(out, members: list[Member], *, case_file, case_args, seeds, sets, reference=None,
              hook=None) -> dict:
    """The ensemble's result (what ``DIR/ensemble.json`` holds) from the member folders under ``out``: the
    members' status, then per parameter combination the statistics of the ok members' metrics, the difference
    from the ``reference`` (a ``load_reference`` pair) and the case's pooled metrics (``hook``)."""
    out = Path(out)
    entries = []
    summaries: dict = {}
    for m in members:
        state, record = member_state(out / m.name)
        status = record["status"] if record else {"interrupted": "interrupted", "new": "not run"}[state]
        entries.append({"name": m.name, "seed": m.seed, "parameters": dict(m.parameters), "status": status,
                        "error": record.get("error") if record else None})
        if status == "ok":
            summaries[m.name] = record.get("summary")
    ref_dir, ref = reference if reference is not None else (None, None)
    combinations = []
    for key, group in itertools.groupby(members, key=lambda m: m.parameters):
        group = list(group)
        params = dict(key)
        ok = [m.name for m in group if m.name in summaries]
        combo = {"name": "_".join(f"{n}={v}" for n, v in key) or "all", "parameters": params,
                 "members": ok, "not_ok": [m.name for m in group if m.name not in summaries],
                 "metrics": _statistics([summaries[n] for n in ok if isinstance(summaries[n], dict)])}
        ref_combo = _match_reference(params, ref) if ref is not None else None
        if ref is not None:
            combo["reference"] = None if ref_combo is None else ref_combo["name"]
            combo["vs_reference"] = None if ref_combo is None else _difference(combo["metrics"], ref_combo["metrics"])
        if hook is not None and ok:
            ref_dirs = None if ref_combo is None else [str(ref_dir / n) for n in ref_combo["members"]]
            combo["pooled"] = _call_hook(hook, [str(out / n) for n in ok], ref_dirs)
        combinations.append(combo)
    counts = {s: sum(e["status"] == s for e in entries) for s in dict.fromkeys(e["status"] for e in entries)}
    return {"case": str(case_file), "case_args": list(case_args), "seeds": list(seeds),
            "parameters": {n: list(v) for n, v in sets}, "reference": None if ref_dir is None else str(ref_dir),
            "counts": counts, "members": entries, "combinations": combinations}


# ------------------------------------------------------------------------------------------------ the driver
def default_workers() -> int:
    """The cores this process may use."""
    if hasattr(os, "sched_getaffinity"):
        return len(os.sched_getaffinity(0))
    return os.cpu_count() or 1


def _client(scheduler: str | None, workers: int):
    """A Dask client: of the scheduler at ``scheduler`` (an address, or a scheduler file), else of a local cluster
    of ``workers`` single-threaded in-process workers (each member is a process of its own anyway; in-process
    workers start at once and die with the driver)."""
    try:
        from dask.distributed import Client, LocalCluster
    except ImportError:
        raise ConfigError("hel-warp ensemble needs dask distributed: pip install 'dask[distributed]'") from None
    if scheduler:
        kw = {"scheduler_file": scheduler} if os.path.isfile(scheduler) else {"address": scheduler}
        try:
            return Client(**kw, timeout=SCHEDULER_TIMEOUT_S), None
        except Exception as exc:  # noqa: BLE001 - connection errors come in many types
            raise ConfigError(f"cannot reach the Dask scheduler at {scheduler!r} ({exc}); check the address or "
                              "scheduler file") from None
    import logging
    import warnings

    with warnings.catch_warnings():  # its health endpoint takes another port when two ensembles run: no matter
        warnings.filterwarnings("ignore", message="Port .* is already in use")
        cluster = LocalCluster(n_workers=workers, threads_per_worker=1, processes=False, dashboard_address=None,
                               silence_logs=logging.ERROR)
    return Client(cluster), cluster


def _spec(member: Member, out: Path, case_file: Path, case_args, options: set[str]) -> dict:
    return {"name": member.name, "dir": str(out / member.name), "log": str(out / LOG_DIR / f"{member.name}.log"),
            "case": str(case_file), "argv": list(case_args) + member.case_options(), "json": "--json" in options,
            "no_progress": "--no-progress" in options, "resume": "--resume" in options,
            "overwrite": "--overwrite" in options, "cwd": os.getcwd()}


def _run_members(specs: list[dict], client, cluster, progress: bool, say) -> list[dict]:
    """Run the members on ``client``'s cluster (closed at the end, with ``cluster`` when a local one); the
    records as they come, failures reported one line each."""
    from dask.distributed import as_completed
    from tqdm import tqdm

    records = []
    bar = None
    _STOPPING.clear()
    completed = False
    try:
        futures = client.map(run_member, specs, pure=False)
        by_key = {f.key: s for f, s in zip(futures, specs)}
        bar = tqdm(total=len(specs), unit="run", desc="ensemble", disable=not progress, file=sys.stderr,
                   mininterval=0.5, dynamic_ncols=True)
        failed = 0
        for future in as_completed(futures):
            try:
                record = future.result()
            except Exception as exc:  # noqa: BLE001 - a worker lost, a task that could not run: reported
                record = {"name": by_key[future.key]["name"], "status": "failed", "ran": True,
                          "error": f"the task failed on the cluster: {type(exc).__name__}: {exc}"}
            records.append(record)
            if record["status"] != "ok":
                failed += 1
                line = f"{record['status']}: {record['name']}: {record['error']}"
                bar.write(line, file=sys.stderr) if progress else say(line)
            bar.update(1)
            if failed:
                bar.set_postfix(failed=failed, refresh=False)
        completed = True
    finally:
        if not completed:
            stop_members()
        if bar is not None:
            bar.close()
        client.close()
        if cluster is not None:
            cluster.close()
    return records


def check_command(out: Path, case_file: Path, case_args) -> dict:
    """The ensemble's command record; ConfigError when ``out`` holds an ensemble of another case or other case
    arguments (its members would mix)."""
    command = {"case": str(case_file), "case_args": list(case_args)}
    old = _read_json(out / COMMAND_JSON)
    if old is not None and old != command:
        raise ConfigError(f"{out} holds an ensemble of {old.get('case')} with the case arguments "
                          f"{shlex.join(old.get('case_args') or [])!r}, not {shlex.join(case_args)!r}; give another "
                          "--out, or the same case and case arguments to extend or resume it")
    return command


def load_hook(case_file: Path):
    """The case module's ``pooled_metrics`` (None when it defines none)."""
    from hel_warp.cli.commands._common import load_case_module

    return getattr(load_case_module(str(case_file)), "pooled_metrics", None)


def run_ensemble(case, seeds, sets, out, case_args=(), *, scheduler: str | None = None, workers: int | None = None,
                 reference=None, progress: bool = True, say=print) -> dict:
    """Run the ensemble and write ``DIR/ensemble.json``; returns its object with ``run`` added (what this
    invocation ran: members run, skipped as finished, wall clock). ``seeds``: a list (``parse_seeds``); ``sets``:
    ``parse_sets``'s list. Bad input raises ConfigError before anything is written."""
    from hel_warp.cli.commands._common import case_path

    start = time.perf_counter()
    case_file = case_path(str(case)).resolve()
    out = Path(out).resolve()
    case_args = list(case_args)
    if not seeds:
        raise ConfigError("no seeds; give --seeds A-B")
    options = case_options(case_file)
    check_case(options, sets, case_args)
    members = plan(seeds, sets)
    ref = load_reference(reference) if reference is not None else None
    if out.exists() and not out.is_dir():
        raise ConfigError(f"--out {out} is a file; give a folder")
    command = check_command(out, case_file, case_args)
    if workers is not None and workers < 1:
        raise ConfigError(f"--workers must be >= 1 (got {workers})")
    states = {m.name: member_state(out / m.name)[0] for m in members}
    todo = [m for m in members if states[m.name] != "finished"]
    client = cluster = None
    if todo:  # a scheduler that does not answer is bad input: refused before anything is written
        client, cluster = _client(scheduler, min(workers or default_workers(), len(todo)))
    try:
        out.mkdir(parents=True, exist_ok=True)
        lock = _lock(out)
        _write_json(out / COMMAND_JSON, command, indent=1)
    except BaseException:
        if client is not None:
            client.close()
            if cluster is not None:
                cluster.close()
        raise
    try:
        records = []
        if todo:
            specs = [_spec(m, out, case_file, case_args, options) for m in todo]
            records = _run_members(specs, client, cluster, progress, say)
        result = _finish(out, members, case_file, case_args, seeds, sets, ref)
    finally:
        if lock is not None:
            lock.close()
    ran = [r["name"] for r in records if r.get("ran")]
    return {**result, "run": {"ran": ran, "skipped": len(members) - len(ran), "members": len(members),
                              "wall_s": time.perf_counter() - start, "out": str(out)}}


def _finish(out: Path, members, case_file, case_args, seeds, sets, ref) -> dict:
    """Summarise the member folders (with the case's pooled metrics) and write ``ensemble.json``."""
    try:
        hook = load_hook(case_file)
    except Exception as exc:  # noqa: BLE001 - the members are on disk; the result says why no pooled metrics
        message = f"the case module could not be loaded for its pooled_metrics: {type(exc).__name__}: {exc}"

        def hook(dirs, ref_dirs, _message=message):
            raise ConfigError(_message)
    result = summarise(out, members, case_file=case_file, case_args=case_args, seeds=seeds, sets=sets,
                       reference=ref, hook=hook)
    _write_json(out / ENSEMBLE_JSON, result, indent=1)
    return result


def _lock(out: Path):
    """Hold ``DIR/.ensemble.lock`` while this driver runs (released by the system when it dies, even killed): a
    second driver on the same DIR would run the same members into the same folders. None where locks are not
    available."""
    try:
        import fcntl
    except ImportError:
        return None
    fh = open(out / ".ensemble.lock", "a+")
    try:
        fcntl.flock(fh, fcntl.LOCK_EX | fcntl.LOCK_NB)
    except OSError:
        fh.seek(0)
        holder = fh.read().strip()
        fh.close()
        raise ConfigError(f"another hel-warp ensemble runs in {out} ({holder or 'a process'}); wait for it, or give "
                          "another --out") from None
    fh.seek(0)
    fh.truncate()
    fh.write(f"pid {os.getpid()} on {socket.gethostname()}\n")
    fh.flush()
    return fh


# ------------------------------------------------------------------------------------------------ the table
def _num(x, spec: str = ".6g") -> str:
    return "-" if x is None else format(x, spec)


def format_table(result: dict) -> str:
    """The printed table: per combination, per metric that differs between its members, n, mean and standard
    error (and the difference from the reference with its error); the pooled metrics; the members not ok."""
    counts = ", ".join(f"{v} {k}" for k, v in result["counts"].items())
    lines = [f"{Path(result['case']).name}: {len(result['members'])} members ({counts})"
             + (f"; reference {result['reference']}" if result.get("reference") else "")]
    has_ref = result.get("reference") is not None
    for combo in result["combinations"]:
        lines.append("")
        lines.append(f"[{combo['name']}] {len(combo['members'])} ok members"
                     + (f", reference [{combo['reference']}]" if has_ref and combo.get("reference") else "")
                     + (" (no matching reference combination)" if has_ref and not combo.get("reference") else ""))
        shown = {k: s for k, s in combo["metrics"].items() if s["varies"]}
        rows = [("metric", "n", "mean", "std. error") + (("vs reference", "std. error") if has_ref else ())]
        vs = combo.get("vs_reference") or {}
        for name, s in shown.items():
            row = (name, str(s["n"]), _num(s["mean"]), _num(s["stderr"], ".3g"))
            if has_ref:
                d = vs.get(name)
                row += (("-", "-") if d is None else (_num(d["difference"], "+.6g"), _num(d["stderr"], ".3g")))
            rows.append(row)
        pooled = (combo.get("pooled") or {})
        if "result" in pooled:
            res = pooled["result"]
            values = scalar_metrics(res["metrics"] if isinstance(res.get("metrics"), dict) else res)
            errors = res.get("stderr") if isinstance(res.get("stderr"), dict) else {}
            for name, v in values.items():
                rows.append((f"pooled: {name}", str(len(combo["members"])), _num(v), _num(errors.get(name), ".3g"))
                            + (("", "") if has_ref else ()))
        if len(rows) > 1:
            widths = [max(len(r[k]) for r in rows) for k in range(len(rows[0]))]
            for r in rows:
                lines.append("  " + "  ".join(c.ljust(w) if k == 0 else c.rjust(w)
                                              for k, (c, w) in enumerate(zip(r, widths))))
        hidden = len(combo["metrics"]) - len(shown)
        if hidden:
            lines.append(f"  ({hidden} metrics the same in every member not shown; {ENSEMBLE_JSON} has them)")
        if "error" in pooled:
            lines.append(f"  pooled metrics failed: {pooled['error']}")
    bad = [e for e in result["members"] if e["status"] != "ok"]
    if bad:
        lines.append("")
        lines.append(f"members not ok ({len(bad)}; a rerun of the same command runs all but the 'check failed' "
                     "ones again):")
        lines += [f"  {e['name']}: {e['status']}" + (f": {e['error']}" if e["error"] else "") for e in bad]
    return "\n".join(lines)
