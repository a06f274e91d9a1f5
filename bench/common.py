"""What the bench scripts share: paths, progress lines, the JSON output, the environment guard, latency statistics.

The machine description (``machine_info``, the ``--wait-quiet`` option, CPU use of other processes) is in
``bench/machine.py``. The benches import both as top-level modules: the script's folder, bench/, is on
``sys.path`` when one runs ``python bench/bench_x.py``.
"""

from __future__ import annotations

import json
import sys
import time
from collections.abc import Callable, Iterator, Sequence
from contextlib import contextmanager
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parents[1]
OUT_DIR = ROOT / "bench" / "out"  # git-ignored
ENV_HINT = "run it after `source scripts/env.sh`"


# -- progress on stderr -------------------------------------------------------------------------------------
def progress_for(name: str) -> Callable[[str], None]:
    """The bench's ``progress(message)``: ``[name HH:MM:SS] message`` on stderr, flushed."""

    def progress(message: str) -> None:
        print(f"[{name} {time.strftime('%H:%M:%S')}] {message}", file=sys.stderr, flush=True)

    return progress


# -- the environment guard ----------------------------------------------------------------------------------
@contextmanager
def requires_env(name: str, hint: str = ENV_HINT) -> Iterator[None]:
    """Imports of tal and its dependencies go in this block: an ImportError there is an environment problem, not
    a benchmark result, and ends the script with ``SystemExit("name: <error>; <hint>")``."""
    try:
        yield
    except ImportError as exc:
        raise SystemExit(f"{name}: {exc}; {hint}") from None


# -- the JSON output ----------------------------------------------------------------------------------------
def json_path(name_or_path: str | Path) -> Path:
    """``bench/out/<name>.json`` for a bench name (a str without "/" or ".json"), else the path itself."""
    if isinstance(name_or_path, str) and "/" not in name_or_path and not name_or_path.endswith(".json"):
        return OUT_DIR / f"{name_or_path}.json"
    return Path(name_or_path)


def write_json(
    name_or_path: str | Path, document: dict, indent: int = 1, log: Callable[[str], None] | None = None
) -> Path:
    """Write ``document`` to ``json_path(name_or_path)`` (creating its folder), indented; with ``log``, say where
    (relative to the repository when inside it). Returns the path."""
    path = json_path(name_or_path)
    path.parent.mkdir(parents=True, exist_ok=True)
    path.write_text(json.dumps(document, indent=indent) + "\n")
    if log is not None:
        resolved = path.resolve()
        log(f"wrote {resolved.relative_to(ROOT) if resolved.is_relative_to(ROOT) else path}")
    return path


# -- statistics -----------------------------------------------------------------------------------------------
STATISTICS: dict[str, Callable[[np.ndarray], float]] = {
    "median": np.median,
    "mean": np.mean,
    "std": np.std,  # population standard deviation (ddof 0)
    "p90": lambda x: np.percentile(x, 90),
    "p99": lambda x: np.percentile(x, 99),
    "max": np.max,
}
# The sets the benches record, in their JSON's key order (bench/report.py reads median, p99, max and mean).
CONTROL_STATS = ("median", "p99", "max", "mean")  # bench_wbc, bench_stance (the default)
ESTIMATOR_STATS = ("median", "p90", "p99", "max", "mean")  # bench_estimator, with its 3 ms budget
VITAL_STATS = ("median", "p99", "mean", "std", "max")  # bench_vfa, bench_vfa_cnn, bench_vpa


def latency_stats(
    samples: Sequence[float] | np.ndarray, fields: Sequence[str] = CONTROL_STATS, *, budget_ms: float | None = None
) -> dict[str, int | float | None]:
    """``n`` and the ``fields`` (names in ``STATISTICS``, in that order) of ``samples``, in the samples' unit
    (ms for times). With ``budget_ms``, also ``median_budget_pct`` and ``p99_budget_pct``: the median's and the
    p99's share of the budget [%] (``fields`` must hold median and p99). Without samples every figure is None."""
    x = np.asarray(samples, dtype=float)
    if x.size == 0:
        out: dict[str, int | float | None] = {"n": 0, **dict.fromkeys(fields)}
    else:
        out = {"n": int(x.size), **{name: float(STATISTICS[name](x)) for name in fields}}
    if budget_ms is not None:
        for name in ("median", "p99"):
            value = out[name]
            out[f"{name}_budget_pct"] = None if value is None else 100.0 * value / budget_ms
    return out


def fmt(value: float | None, digits: int = 3) -> str:
    """A figure for a markdown table: ``digits`` decimals, "n/a" for None."""
    return "n/a" if value is None else f"{value:.{digits}f}"
