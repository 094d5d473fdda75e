"""Figures of a trained model (reference paper, Figs. 7 and 8) into ``MODEL_DIR/report/``.

- ``parity.png``: predicted vs true post-collision u, v, w of particle 1 on the test set,
  with the diagonal and each component's MAE (Fig. 7);
- ``relative_error.png``: histogram of the relative velocity error
  ``|u1_pred - u1| / |u1|`` in percent, with the share below 5 % (Fig. 8);
- ``metrics.json``: the test-set metrics.
"""

from __future__ import annotations

import json
import os

import numpy as np


def write_report(model_dir: str, u1_true, u1_pred, rel_err, metrics: dict) -> list[str]:
    """Write the two figures and metrics.json; return the paths written."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    out_dir = os.path.join(model_dir, "report")
    os.makedirs(out_dir, exist_ok=True)
    u1_true, u1_pred = np.asarray(u1_true), np.asarray(u1_pred)
    form = metrics.get("form", "?")
    fig, axes = plt.subplots(1, 3, figsize=(13, 4.4), constrained_layout=True)
    for k, (ax, name) in enumerate(zip(axes, ("u", "v", "w"))):
        t, p = u1_true[:, k], u1_pred[:, k]
        lo, hi = float(min(t.min(), p.min())), float(max(t.max(), p.max()))
        ax.scatter(t, p, s=4, alpha=0.5, color="tab:blue", edgecolors="none")
        ax.plot([lo, hi], [lo, hi], color="red", lw=1.2, label="diagonal")
        mae = float(np.mean(np.abs(p - t)))
        ax.set_title(f"{name}: MAE = {mae:.4f} m/s")
        ax.set_xlabel(f"true {name} after collision (m/s)")
        ax.set_ylabel(f"predicted {name} (m/s)")
        ax.grid(alpha=0.3)
    fig.suptitle(f"Test set, particle 1 ({form} form, n = {u1_true.shape[0]})")
    parity = os.path.join(out_dir, "parity.png")
    fig.savefig(parity, dpi=110)
    plt.close(fig)

    rel_pct = 100.0 * np.asarray(rel_err)
    fig, ax = plt.subplots(figsize=(6.5, 4.2), constrained_layout=True)
    upper = max(20.0, float(np.percentile(rel_pct, 99))) if rel_pct.size else 20.0
    bins = np.linspace(0.0, upper, 41)
    ax.hist(np.clip(rel_pct, 0, upper), bins=bins, color="tab:blue", edgecolor="white",
            weights=np.full(rel_pct.size, 100.0 / max(rel_pct.size, 1)))
    ax.axvline(5.0, color="red", lw=1.2, label=f"5 %: {100 * np.mean(rel_pct < 5):.1f} % of rows below")
    ax.set_xlabel("relative error |u1_pred - u1| / |u1| (%)  (last bin: all above)")
    ax.set_ylabel("share of test rows (%)")
    ax.set_title(f"Relative velocity error ({form} form)")
    ax.legend()
    hist = os.path.join(out_dir, "relative_error.png")
    fig.savefig(hist, dpi=110)
    plt.close(fig)

    metrics_path = os.path.join(out_dir, "metrics.json")
    with open(metrics_path, "w") as fh:
        json.dump(metrics, fh, indent=2)
    return [parity, hist, metrics_path]
