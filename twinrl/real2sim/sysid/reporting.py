"""Reporting a sysid fit: ``print_result`` (a table of values, sd and status) and, for evaluation
only, ``compare_to_truth`` (errors against a real twin's hidden parameters, which learning code
never sees).
"""

from __future__ import annotations

import math
from typing import Any

import numpy as np

from twinrl.physics import PhysParams
from twinrl.real2sim.sysid.fit import SysidResult
from twinrl.real2sim.sysid.problem import as_f64, dvalue_du, param_value

__all__ = ["compare_to_truth", "print_result"]


def compare_to_truth(result: SysidResult, truth: PhysParams,
                     true_latency: int | None = None) -> list[dict[str, Any]]:
    """Evaluation only: each fitted parameter against its true value.

    ``truth`` is the real twin's true ``PhysParams`` (its oracle's ``params``), which learning
    code never sees. Rows: parameter, truth, identified, sd, rel_err (|identified - truth| /
    |truth|; absolute error where the truth is 0), covered (|error| <= 3 sd), identifiable, and
    -- where the parameter is only identifiable in combination (overall scale) -- ``aligned``:
    the identified value after the one common scale factor that best matches the truth, with its
    ``aligned_rel_err`` and ``aligned_covered`` (against the sd along the identifiable
    directions). A ``latency`` row is added when ``true_latency`` is given.
    """
    t = as_f64(truth).as_dict()
    rows = []
    combo = [j for j, s in enumerate(result.status) if s.startswith("only in combination")]
    aligned = result.values.copy()
    if combo:
        true_v = np.array([param_value(t, *_split(n, result))
                           for n in np.array(result.names)[combo]])
        ok = (true_v > 0) & (result.values[combo] > 0)
        logc = float(np.mean(np.log(true_v[ok] / result.values[combo][ok]))) if ok.any() else 0.0
        aligned[combo] = result.values[combo] * math.exp(logc)
    sd_data = np.sqrt(np.maximum(np.diag(result.cov_u_data), 0.0))
    for j, name in enumerate(result.names):
        tv = param_value(t, *_split(name, result))
        v, s = float(result.values[j]), float(result.sd[j])
        err = abs(v - tv)
        row = dict(parameter=name, truth=tv, identified=v, sd=s,
                   rel_err=err / abs(tv) if tv != 0 else err, covered=bool(err <= 3 * s + 1e-12),
                   identifiable=bool(result.identifiable[j]), status=result.status[j])
        if j in combo:
            f = _split(name, result)[0]
            s_al = abs(dvalue_du(f, result.theta_u[j])) * sd_data[j] * aligned[j] / max(v, 1e-300)
            e_al = abs(aligned[j] - tv)
            row.update(aligned=float(aligned[j]), aligned_sd=float(s_al),
                       aligned_rel_err=e_al / abs(tv) if tv != 0 else e_al,
                       aligned_covered=bool(e_al <= 3 * s_al + 1e-12))
        rows.append(row)
    if true_latency is not None:
        rows.append(dict(parameter="latency", truth=int(true_latency), identified=result.latency,
                         sd=0.0, rel_err=float(result.latency != true_latency),
                         covered=result.latency == true_latency, identifiable=True,
                         status="identified"))
    return rows


def _split(name: str, result: SysidResult) -> tuple[str, int]:
    return result.spec[result.names.index(name)]


def print_result(result: SysidResult, truth_rows: list[dict] | None = None,
                 title: str = "sysid") -> None:
    """Print the report table (with truth columns when ``compare_to_truth`` rows are given)."""
    from twinrl import report
    if truth_rows is None:
        cols = ["parameter", "initial", "identified", "sd", "identifiable"]
        rows = [[r["parameter"], r["initial"], r["identified"], r["sd"], r["status"]]
                for r in result.table]
    else:
        cols = ["parameter", "initial", "identified", "sd", "identifiable", "truth", "rel err",
                "|err|<=3sd"]
        init = {r["parameter"]: r["initial"] for r in result.table}
        rows = [[r["parameter"], init.get(r["parameter"], "-"), r["identified"], r["sd"],
                 r["status"], r["truth"], r["rel_err"], "yes" if r["covered"] else "NO"]
                for r in truth_rows]
    rows.append(["latency", "-", result.latency, "-", "chosen by loss", "", "", ""][:len(cols)])
    report.print_table(f"{title}: loss {result.loss:.3g}, {result.n_windows} windows, "
                       f"{result.sim_rollouts} window rollouts, {result.seconds:.1f} s",
                       cols, rows)
