"""Surrogate models for a flow: checked against its particles, or built on first use and cached.

A surrogate is valid only where its data are: the particle sizes, densities and material of the binary DEM
collisions it was trained on (``metadata.json``: ``defaults`` d1 and rho1, ``material``, the training
``domain``). :func:`check_model` refuses a model trained for other particles with one line naming the
difference. :func:`model_for` returns a model for the flow's species and material: from the cache
(``hel_warp.case.packing.cache_dir() / "models"``, keyed by the species and material) or, the first time,
built by ``hel-warp dataset`` then ``hel-warp train --form contact`` at the sizes ``AUTO_SAMPLES`` /
``AUTO_TRIALS`` (a few minutes on one CPU core), so that a user of a case needs neither command.
"""

from __future__ import annotations

import contextlib
import fcntl
import hashlib
import json
import os
import shutil
import sys
import time

from hel_warp.errors import ConfigError

AUTO_SAMPLES = 20000
"""Binary DEM collisions of an automatically built data set (``hel-warp demo``'s size)."""
AUTO_TRIALS = 4
"""Optuna trials per target of an automatically trained model."""
MATERIAL_FIELDS = ("youngs_modulus", "poisson_ratio", "restitution", "friction")


def read_metadata(model_dir: str) -> dict:
    path = os.path.join(model_dir, "metadata.json")
    if not os.path.isdir(model_dir):
        raise ConfigError(f"--model {model_dir}: no such directory; give a directory written by `hel-warp train`")
    try:
        with open(path) as fh:
            meta = json.load(fh)
    except FileNotFoundError:
        raise ConfigError(f"--model {model_dir}: {path} not found; give a directory written by `hel-warp train`") \
            from None
    except (json.JSONDecodeError, UnicodeDecodeError) as exc:
        raise ConfigError(f"--model {model_dir}: {path} is not valid JSON ({exc})") from None
    if not isinstance(meta, dict):
        raise ConfigError(f"--model {model_dir}: {path} does not hold a JSON object")
    return meta


def model_material(meta: dict) -> dict | None:
    """The DEM material the model's data set was made with (a dict of ``Material`` fields), or None."""
    for where in (meta.get("material"), (meta.get("dataset") or {}).get("material"),
                  (meta.get("defaults") or {}).get("material")):
        if isinstance(where, dict):
            return where
    return None


def check_model(model_dir: str, species, *, force: bool = False, force_flag: str = "--force",
                check_material: bool = True) -> dict:
    """Refuse a surrogate trained for other particles (returns its metadata).

    ``species``: the flow's species. One size: the model's mean diameter within 10 % of the species' (a size
    distribution of +-3 sigma spans +-8 % at 315 um) and its density within 1 %; several sizes: a training domain
    holding every size and size ratio (``hel_warp.collisions.mixture.model_domain_problem``). ``check_material``: also the
    elastic and frictional constants within 1 % when the metadata records them. ``force`` lets it pass anyway.
    """
    meta = read_metadata(model_dir)
    defaults = meta.get("defaults")
    problems = []
    if not isinstance(defaults, dict) or "d1" not in defaults or "rho1" not in defaults:
        problems.append("its metadata does not record the particle size and density it was trained for")
    else:
        d_model, rho_model = float(defaults["d1"]), float(defaults["rho1"])
        diameters = [s.diameter for s in species]
        if len(set(diameters)) > 1:
            from hel_warp.collisions.mixture import model_domain_problem

            problem = model_domain_problem(meta, diameters)
            if problem:
                problems.append(problem)
        elif abs(d_model - diameters[0]) > 0.10 * diameters[0]:
            problems.append(f"it was trained for d = {d_model * 1e6:.0f} um, the run has {diameters[0] * 1e6:.0f} um")
        density = species[0].density
        if abs(rho_model - density) > 0.01 * density:
            problems.append(f"it was trained for density {rho_model:g} kg/m^3, the run has {density:g} kg/m^3")
    recorded = model_material(meta)
    if check_material and recorded:
        material = species[0].material
        for name in MATERIAL_FIELDS:
            if name in recorded:
                ours, theirs = float(getattr(material, name)), float(recorded[name])
                if abs(ours - theirs) > 0.01 * max(abs(ours), 1e-12):
                    problems.append(f"it was trained with {name} {theirs:g}, the run's material has {ours:g}")
    if problems and not force:
        raise ConfigError(f"model {model_dir}: {'; '.join(problems)}; train a model for these particles (or run "
                          f"without --model to build one) or pass {force_flag} to use it anyway")
    return meta


def _key(species, form: str) -> str:
    payload = {"form": form, "samples": AUTO_SAMPLES, "trials": AUTO_TRIALS, "version": 1,
               "species": [{"d": s.diameter, "sd": s.diameter_std, "rho": s.density,
                            **{n: getattr(s.material, n) for n in MATERIAL_FIELDS}} for s in species]}
    return hashlib.sha256(json.dumps(payload, sort_keys=True).encode()).hexdigest()[:16]


def model_for(species, *, form: str = "contact", announce=print) -> str:
    """A contact-form model directory for ``species`` (module docstring): cached, or built now."""
    from hel_warp.case.packing import cache_dir

    materials = {tuple(getattr(s.material, n) for n in ("density",) + MATERIAL_FIELDS) for s in species}
    if len(materials) > 1:
        raise ConfigError("an automatic surrogate needs one material for every species; give --model for a mixture "
                          "of materials")
    root = cache_dir() / "models" / _key(species, form)
    model_dir = root / "model"
    if (model_dir / "metadata.json").exists() and _readable(model_dir):
        return str(model_dir)
    root.mkdir(parents=True, exist_ok=True)
    # Members of an ensemble start together and would build the same model side by side, writing into one folder:
    # the first takes the lock and builds, the others wait for it and then find the model.
    with open(root / ".lock", "w") as lock:
        fcntl.flock(lock, fcntl.LOCK_EX)
        try:
            if (model_dir / "metadata.json").exists():
                if _readable(model_dir):
                    return str(model_dir)
                # a cache entry edited or damaged since it was built: set aside (not deleted), then built again
                aside = root / f"model.unreadable-{int(time.time())}"
                os.replace(model_dir, aside)
                announce(f"hel-warp: warning: the cached surrogate in {model_dir} no longer loads; moved to {aside} "
                         "and built again")
            return _build_model(species, form, root, model_dir, announce)
        finally:
            fcntl.flock(lock, fcntl.LOCK_UN)


def _readable(model_dir) -> bool:
    """Whether the cached model loads: its forest.json parses and matches the sha256 its metadata records."""
    from hel_warp.collisions.forest import load_forest

    try:
        load_forest(str(model_dir))
    except ConfigError:
        return False
    return True


def _build_model(species, form, root, model_dir, announce) -> str:
    from hel_warp.cli import main as cli_main

    m = species[0].material
    data_dir = root / "dataset"
    size = ["--diameter", repr(species[0].diameter), "--diameter-std", repr(species[0].diameter_std)]
    if len(species) > 1:
        size = ["--diameters", ",".join(repr(s.diameter) for s in species),
                "--diameter-stds", ",".join(repr(s.diameter_std) for s in species)]
    announce(f"building a surrogate for {', '.join(f'{s.diameter * 1e6:.0f} um' for s in species)} "
             f"(rho {m.density:g}, E {m.youngs_modulus:g}, nu {m.poisson_ratio:g}, e {m.restitution:g}, "
             f"mu {m.friction:g}): {AUTO_SAMPLES} binary DEM collisions, then {AUTO_TRIALS} Optuna trials per target; "
             f"cached in {root}")
    # the data set's and the training's reports go to stderr: a case's stdout is its --json summary alone
    with contextlib.redirect_stdout(sys.stderr):
        code = cli_main(["dataset", "--out", str(data_dir), "--samples", str(AUTO_SAMPLES), *size, "--seed", "0",
                         "--density", repr(m.density), "--youngs", repr(m.youngs_modulus), "--poisson",
                         repr(m.poisson_ratio), "--restitution", repr(m.restitution), "--friction",
                         repr(m.friction), "--no-progress"])
        if code:
            raise ConfigError(f"building the data set for the automatic surrogate failed (exit {code}); see above")
        tmp = root / "model.tmp"
        if tmp.exists():
            shutil.rmtree(tmp)
        code = cli_main(["train", "--data", str(data_dir), "--out", str(tmp), "--form", form, "--trials",
                         str(AUTO_TRIALS), "--jobs", "1"])
    if code:
        raise ConfigError(f"training the automatic surrogate failed (exit {code}); see above")
    os.replace(tmp, model_dir)
    return str(model_dir)


def surrogate_domain(model_dir: str) -> dict:
    """The training domain a model states (its metadata's ``domain``), for the summary of a run."""
    meta = read_metadata(model_dir)
    return {"dataset_hash": meta.get("dataset_hash"), "form": meta.get("form"), "defaults": meta.get("defaults"),
            "domain": meta.get("domain"), "material": model_material(meta)}


__all__ = ["check_model", "model_for", "read_metadata", "surrogate_domain"]
