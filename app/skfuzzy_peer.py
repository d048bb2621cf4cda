"""The thesis rule base built in scikit-fuzzy: the oracle of the tests and
the peer of ``cwrr bench perf``. scikit-fuzzy is a test/benchmark extra, not
a run-time dependency; importing this module without it raises ImportError."""

from __future__ import annotations

from typing import Any

import numpy as np
import skfuzzy as fuzz
from skfuzzy import control as ctrl

from app.engine.control.fuzzy import GAINS, INPUT_LABELS, OUTPUT_LABELS, RULES, FuzzyConfig


def build_skfuzzy(config: FuzzyConfig, output_points: int = 40001) -> Any:
    """A ``ControlSystemSimulation`` with inputs ``e``/``de`` and outputs ``kp``/``ki``/``kd``.

    Args:
        config: Our configuration; its MFs are copied, and the centroid
            defuzzifier is used (skfuzzy has no Eq 3.27).
        output_points: Samples of the output universe. skfuzzy integrates the
            aggregated set piecewise-linearly between samples and misses kinks
            between them, an error of order (1/points)²: 40001 points bring it
            below 1e-9.
    """
    e_mfs, de_mfs = config.input_mfs()
    ue = np.unique(np.concatenate([np.linspace(e_mfs[0, 1], e_mfs[-1, 1], 601), e_mfs.ravel()]))
    ud = np.unique(np.concatenate([np.linspace(de_mfs[0, 1], de_mfs[-1, 1], 601), de_mfs.ravel()]))
    out_mfs = np.asarray(config.out_mfs, dtype=float)
    uo = np.unique(np.concatenate([np.linspace(0.0, 1.0, output_points), out_mfs.ravel()]))
    e = ctrl.Antecedent(ue, "e")
    d = ctrl.Antecedent(ud, "de")
    for lab, tri in zip(INPUT_LABELS, e_mfs, strict=True):
        e[lab] = fuzz.trimf(ue, tri)
    for lab, tri in zip(INPUT_LABELS, de_mfs, strict=True):
        d[lab] = fuzz.trimf(ud, tri)
    rules = []
    for g, name in enumerate(GAINS):
        o = ctrl.Consequent(uo, name, defuzzify_method="centroid")
        for lab, tri in zip(OUTPUT_LABELS, out_mfs, strict=True):
            o[lab] = fuzz.trimf(uo, tri)
        for r in range(7):
            for c in range(7):
                rules.append(ctrl.Rule(d[INPUT_LABELS[r]] & e[INPUT_LABELS[c]], o[OUTPUT_LABELS[RULES[g, r, c]]]))
    return ctrl.ControlSystemSimulation(ctrl.ControlSystem(rules), clip_to_bounds=True)
