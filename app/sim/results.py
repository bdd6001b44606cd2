"""A campaign's results on disk, and what they say with how sure we are.

- :class:`ResultLog`: ``encounters.csv`` appended one row per finished encounter (flushed and
  fsynced at once), so that a campaign cut short by Ctrl-C, a lost worker or a power cut keeps
  everything it finished; with ``campaign.json`` beside it (what was asked for), ``--resume``
  runs only what is missing, and refuses to mix results of another configuration.
- :func:`poisson_upper`: the upper confidence bound of a rate of rare events (false evasions
  per flight hour) from a count over an exposure.
- :func:`compare`: whether two campaigns of the same encounters differ beyond chance (exact
  McNemar test on the pairs whose outcome differs).
"""

from __future__ import annotations

import csv
import dataclasses
import functools
import hashlib
import json
import math
import os
import typing
from collections.abc import Iterable
from pathlib import Path
from typing import Any

from app.errors import UsageError
from app.sim.simulate import Encounter, EncounterResult

CSV_NAME = "encounters.csv"
PLAN_NAME = "campaign.json"


def _parse(text: str, hint: Any) -> Any:
    """One CSV cell back to the type of its field (``hint``, resolved; '' is None)."""
    args = typing.get_args(hint) or (hint,)
    if text == "" and type(None) in args:
        return None
    base = next(a for a in args if a is not type(None))
    if base is bool:
        if text not in ("True", "False"):
            raise ValueError(f"not a bool: {text!r}")
        return text == "True"
    if base in (int, float):
        return base(text)
    return text


@functools.cache
def _hints() -> tuple[dict[str, Any], dict[str, Any]]:
    return typing.get_type_hints(EncounterResult), typing.get_type_hints(Encounter)


def result_from_row(row: dict[str, str]) -> EncounterResult:
    """The inverse of :meth:`EncounterResult.row` (one ``encounters.csv`` row; a column a
    campaign of an older version did not write takes its default)."""
    hints, enc_hints = _hints()
    enc = Encounter(**{f.name: _parse(row[f"enc_{f.name}"], enc_hints[f.name])
                       for f in dataclasses.fields(Encounter) if f"enc_{f.name}" in row})
    values = {f.name: _parse(row[f.name], hints[f.name])
              for f in dataclasses.fields(EncounterResult) if f.name != "encounter" and f.name in row}
    return EncounterResult(encounter=enc, **values)


def config_digest(cfg: object) -> str:
    """A short fingerprint of a configuration (its repr is a complete, ordered dump)."""
    return hashlib.sha256(repr(cfg).encode()).hexdigest()[:16]


class ResultLog:
    """``encounters.csv`` in ``folder``, written as results arrive.

    ``plan`` is what the campaign was asked for (seed, counts, fps, config fingerprint). With
    ``resume`` the folder must hold the same plan, and its results are kept; without, a folder
    that already holds results is refused (nothing is overwritten)."""

    def __init__(self, folder: Path, plan: dict[str, Any], resume: bool) -> None:
        self.folder = folder
        self.path = folder / CSV_NAME
        folder.mkdir(parents=True, exist_ok=True)
        plan_path = folder / PLAN_NAME
        self.done: dict[int, EncounterResult] = {}
        if resume:
            if not plan_path.exists():
                raise UsageError(f"--resume {folder}: no {PLAN_NAME} there (not a campaign folder)")
            old = json.loads(plan_path.read_text())
            if old != plan:
                diff = sorted(k for k in set(old) | set(plan) if old.get(k) != plan.get(k))
                raise UsageError(f"--resume {folder}: that campaign was run with other settings "
                                 f"({', '.join(diff)} differ); run with the same command line")
            for r in self._read():
                self.done[r.encounter.seed] = r
        else:
            held = self._count_rows()
            if held:
                raise UsageError(f"{folder} already holds a campaign's results ({held} encounters in "
                                 f"{CSV_NAME}): --resume {folder} continues it; or choose another --out")
            self.path.unlink(missing_ok=True)
            plan_path.write_text(json.dumps(plan, indent=2) + "\n")
        self._fh = self.path.open("a", newline="")
        self._writer: csv.DictWriter[str] | None = None
        if self.done:
            self._writer = csv.DictWriter(self._fh, fieldnames=list(next(iter(self.done.values())).row()))

    def _count_rows(self) -> int:
        if not self.path.exists():
            return 0
        with self.path.open(newline="") as fh:
            return sum(1 for _ in csv.DictReader(fh))

    def _read(self) -> list[EncounterResult]:
        if not self.path.exists():
            return []
        out = []
        with self.path.open(newline="") as fh:
            for i, row in enumerate(csv.DictReader(fh), start=2):
                if None in row or any(v is None for v in row.values()):
                    break  # a row cut short by the interruption: run that encounter again
                try:
                    out.append(result_from_row(row))
                except (KeyError, ValueError) as exc:
                    raise UsageError(f"{self.path}:{i}: unreadable row ({exc}); "
                                     "move the file away to start afresh") from None
        # rewrite without a torn last line, so appending continues on a clean row
        if out:
            tmp = self.path.with_suffix(".csv.tmp")
            with tmp.open("w", newline="") as fh:
                w = csv.DictWriter(fh, fieldnames=list(out[0].row()))
                w.writeheader()
                w.writerows(r.row() for r in out)
            tmp.replace(self.path)
        return out

    def append(self, result: EncounterResult) -> None:
        row = result.row()
        if self._writer is None:
            self._writer = csv.DictWriter(self._fh, fieldnames=list(row))
            if self._fh.tell() == 0:
                self._writer.writeheader()
        self._writer.writerow(row)
        self._fh.flush()
        os.fsync(self._fh.fileno())
        self.done[result.encounter.seed] = result

    def close(self) -> None:
        self._fh.close()


def read_results(folder: Path) -> list[EncounterResult]:
    """Every result a campaign folder holds (``encounters.csv``)."""
    path = folder / CSV_NAME
    if not path.exists():
        raise UsageError(f"{folder}: no {CSV_NAME} (run `midair simulate --campaign N --out {folder}`)")
    with path.open(newline="") as fh:
        try:
            return [result_from_row(row) for row in csv.DictReader(fh)]
        except (KeyError, ValueError, TypeError) as exc:
            raise UsageError(f"{path}: not a midair campaign's results ({exc})") from None


# ---------------------------------------------------------------------------- statistics


def wilson(k: int, n: int, z: float = 1.96) -> tuple[float, float]:
    """Wilson score interval of a rate k/n (95 % for z = 1.96; Wilson 1927)."""
    if n == 0:
        return (0.0, 1.0)
    p = k / n
    centre = (p + z * z / (2 * n)) / (1 + z * z / n)
    half = z * math.sqrt(p * (1 - p) / n + z * z / (4 * n * n)) / (1 + z * z / n)
    return (max(0.0, centre - half), min(1.0, centre + half))


def poisson_upper(k: int, exposure: float, confidence: float = 0.95) -> float:
    """One-sided upper confidence bound of a Poisson rate: ``k`` events seen over
    ``exposure`` (e.g. flight hours). Exact (Garwood 1936): chi2(confidence, 2k + 2) / 2;
    with no event at 95 % it is 3.0 / exposure, the "rule of three"."""
    from scipy.stats import chi2

    if exposure <= 0:
        return math.inf
    return float(chi2.ppf(confidence, 2 * k + 2)) / 2.0 / exposure


@dataclasses.dataclass
class Comparison:
    pairs: int  # threat encounters in both campaigns (same seed)
    a_only: int  # avoided in A, not in B
    b_only: int
    rate_a: float
    rate_b: float
    p_value: float  # exact McNemar (two-sided binomial test on the discordant pairs)

    @property
    def differ(self) -> bool:
        return self.p_value < 0.05

    def text(self, name_a: str, name_b: str) -> str:
        n = self.pairs
        ka, kb = round(self.rate_a * n), round(self.rate_b * n)
        (la, ha), (lb, hb) = wilson(ka, n), wilson(kb, n)
        verdict = ("differ beyond chance" if self.differ else
                   "do not differ beyond chance (a difference this size can be noise)")
        return (f"{n} threat encounters flown in both (paired by encounter seed)\n"
                f"A {name_a}: {self.rate_a:.1%} avoided ({ka}/{n}; {la:.0%}-{ha:.0%})\n"
                f"B {name_b}: {self.rate_b:.1%} avoided ({kb}/{n}; {lb:.0%}-{hb:.0%})\n"
                f"avoided by A only: {self.a_only}, by B only: {self.b_only}; exact McNemar "
                f"p = {self.p_value:.3g}: the two {verdict}")


def compare(a: Iterable[EncounterResult], b: Iterable[EncounterResult]) -> Comparison:
    """Pair two campaigns' threat encounters by seed and test whether their success differs.
    Paired, because the encounters are the same: only the pairs whose outcome differs carry
    information (McNemar 1947), and under "no difference" either side wins each with 1/2."""
    from scipy.stats import binomtest

    by_a = {r.encounter.seed: r for r in a if r.threat}
    by_b = {r.encounter.seed: r for r in b if r.threat}
    seeds = sorted(set(by_a) & set(by_b))
    if not seeds:
        raise UsageError("compare: the two campaigns share no threat encounter (same --seed?)")
    a_only = sum(by_a[s].success and not by_b[s].success for s in seeds)
    b_only = sum(by_b[s].success and not by_a[s].success for s in seeds)
    n = len(seeds)
    p = 1.0 if a_only + b_only == 0 else float(binomtest(a_only, a_only + b_only, 0.5).pvalue)
    return Comparison(n, a_only, b_only, sum(by_a[s].success for s in seeds) / n,
                      sum(by_b[s].success for s in seeds) / n, p)
