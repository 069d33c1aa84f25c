"""Silverbox at full scale: the Duffing grey box trained on the whole multisine part.

``PYTHONPATH=examples python -m silverbox.full_record`` (needs the Silverbox data, see
``examples/README.md``; ``--n-train N`` for a shorter segment, ``--n-iter K``) fits, on all of the
multisine part (with 5 % injected outliers, and clean), and prints the arrow RMSE (full, and
without the extrapolated tail) and the fit time of

* the robust simulation-error fit alone (``first_stage="simulation"``, ``n_iter=0``): the
  output-error baseline a user would try first, with a Cauchy loss;
* EM after it with Gaussian measurement noise (the Gaussian fit);
* EM after it with Student-t measurement noise (the robust model),

both EM fits with the process noise held small (``fit_Rw=False``, ``Rw_init=1e-6``: a simulation
model, docs/design.md) and the time-parallel E-step (``segment_length=1000``, ``segment_overlap=100``;
the record is ~87,000 samples).
"""

from __future__ import annotations

import argparse

import numpy as np
import torch

from silverbox.data import SILVERBOX_ARROW_END, load_silverbox
from silverbox.first_stage_comparison import estimator, fit_and_score  # the same grey box and settings
from silverbox.study import PUBLISHED_RMSE_MV, prepare_silverbox

HELD = dict(
    first_stage="simulation", fit_Rw=False, Rw_init=[1e-6, 1e-6], segment_length=1000, segment_overlap=100
)
SETTINGS = {
    "robust simulation-error fit (first stage alone)": dict(first_stage="simulation", n_iter=0),
    "EM, Gaussian noise (after the first stage, Rw held)": dict(noise="gaussian", **HELD),
    "EM, Student-t noise (after the first stage, Rw held)": dict(noise="student-t", **HELD),
    # the defaults (first_stage="auto", fit_Rw="auto"), with the long-record E-step
    "EM, Student-t noise, defaults": dict(segment_length=1000, segment_overlap=100),
    # without the first stage, from the equation-error start, Rw free: what EM alone does
    "EM, Gaussian noise (equation-error start, Rw free)": dict(
        noise="gaussian", first_stage=None, fit_Rw=True, segment_length=1000, segment_overlap=100
    ),
    "EM, Student-t noise (equation-error start, Rw free)": dict(
        noise="student-t", first_stage=None, fit_Rw=True, segment_length=1000, segment_overlap=100
    ),
}


def main(argv=None) -> list[dict]:
    p = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("--n-train", type=int, default=None, help="training samples (default: all the multisine)")
    p.add_argument("--n-iter", type=int, default=15)
    p.add_argument("--only", nargs="*", default=None, help="run the fits whose names contain these words")
    a = p.parse_args(argv)
    torch.set_num_threads(1)
    u_all, _ = load_silverbox(part="all")
    n_train = a.n_train or (u_all.shape[0] - SILVERBOX_ARROW_END)
    print(f"training samples: {n_train}; EM iterations: {a.n_iter}")
    print(
        "| training data | fit | arrow RMSE full (mV) | without extrapolation (mV) | dof "
        "| injected outliers weighted < 0.5 | seconds |"
    )
    print("|---|---|---|---|---|---|---|")
    rows = []
    for label, fraction in (("5 % outliers", 0.05), ("clean", 0.0)):
        data = prepare_silverbox(n_train=n_train, outlier_fraction=fraction, random_state=0)
        for name, overrides in SETTINGS.items():
            if a.only and not any(word in name for word in a.only):
                continue
            est = estimator(data, **{"n_iter": a.n_iter, "average_last": min(5, a.n_iter), **overrides})
            rmse, seconds = fit_and_score(est, data)
            dof = "-" if est.n_iter_ == 0 or est.noise == "gaussian" else f"{est.dof_:.2f}"
            detected = "-"
            if est.n_iter_ and est.noise != "gaussian" and data.outlier_mask.any():
                detected = f"{np.mean(np.asarray(est.outlier_weights_)[data.outlier_mask] < 0.5):.0%}"
            full, short = rmse["full"], rmse["no_extrapolation"]
            rows.append(dict(data=label, fit=name, full=full, short=short, seconds=seconds))
            print(
                f"| {label} | {name} | {full:.2f} | {short:.2f} | {dof} | {detected} | {seconds:.0f} |",
                flush=True,
            )
    print(
        f"| published (SUBNET) | | {PUBLISHED_RMSE_MV['full']:.1f} | "
        f"{PUBLISHED_RMSE_MV['no_extrapolation']:.1f} | | | |"
    )
    return rows


if __name__ == "__main__":
    main()
