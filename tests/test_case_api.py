"""The case API (hel_warp.case): a user's mistakes are refused in one line before anything runs, a run resumed from
its checkpoint ends where an uninterrupted one does (bit for bit), and the shared options act in any case."""

import json
import math
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest

from hel_warp import case as hc
from hel_warp.errors import ConfigError

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))

from tests.test_collision_models import train_tiny_models  # noqa: E402
from tests.test_swept import write_constant_contact_forest  # noqa: E402


@pytest.fixture(scope="session")
def tiny_models(tmp_path_factory):
    root = tmp_path_factory.getbasetemp() / "tiny_collision_models"
    root.mkdir(exist_ok=True)
    return train_tiny_models(root)


def small_flow(**gas):
    flow = hc.Flow("box", lo=(0, 0, 0), hi=(4e-3, 4e-3, 12e-3), spacing=1e-3, gravity=(0, 0, -9.81),
                   gas=hc.Gas(**gas) if gas else hc.Gas())
    flow.species("glass", 300e-6, density=2500.0)
    return flow


def build(flow, **settings):
    return hc.build(flow, hc.Settings(**{"collisions": "none", "dt": 1e-4, **settings}))


@pytest.mark.parametrize("mistake, message", [
    (lambda f: f.inlet("in", "w+", 1.0), "face must be one of"),
    (lambda f: f.inlet("in", "z-", -1.0), "blows out of the domain"),
    (lambda f: f.inlet("in", "z-", math.nan), "finite"),
    (lambda f: f.fill("glass", ((0, 0, 0), (4e-3, 4e-3, 2e-3)), solids_fraction=0.7), "random close packing"),
    (lambda f: f.fill("glass", ((0, 0, 0), (4e-3, 4e-3, 2e-3)), count=10**7), "more than random close packing"),
    (lambda f: f.fill("glass", ((1, 1, 1), (2, 2, 2)), count=10), "outside the domain"),
    (lambda f: f.fill("sand", ((0, 0, 0), (4e-3, 4e-3, 2e-3)), count=10), "no species named 'sand'"),
])
def test_a_mistake_in_the_flow_is_one_line_naming_what_to_change(mistake, message):
    flow = small_flow()
    with pytest.raises(ConfigError, match=message) as err:
        mistake(flow)
        flow.fill("glass", ((0, 0, 0), (4e-3, 4e-3, 6e-3)), count=50)
        build(flow)
    assert "\n" not in str(err.value)


def test_an_inlet_patch_on_no_fluid_face_is_refused():
    flow = small_flow()
    flow.inlet("in", "z-", 1.0, lo=(10e-3, 10e-3, 0), hi=(11e-3, 11e-3, 0))  # beside the box, not on it
    flow.outlet("out", "z+")
    flow.fill("glass", ((0, 0, 0), (4e-3, 4e-3, 6e-3)), count=50)
    with pytest.raises(ConfigError, match="covers no fluid cell"):
        build(flow)


def test_a_geometry_with_no_fluid_cell_is_refused():
    flow = hc.Flow("box", lo=(0, 0, 0), hi=(4e-3, 4e-3, 12e-3), spacing=1e-3,
                   shapes=(hc.Box(lo=(20e-3, 20e-3, 20e-3), hi=(30e-3, 30e-3, 30e-3)),))
    flow.species("glass", 300e-6, density=2500.0)
    flow.fill("glass", ((0, 0, 0), (4e-3, 4e-3, 6e-3)), count=50)
    with pytest.raises(ConfigError, match="no cell centre lies inside the geometry"):
        build(flow)


def test_a_surrogate_for_other_particles_is_refused(tiny_models):
    from hel_warp.case.models import check_model

    model = str(tiny_models["contact"])
    flow = small_flow()  # 300 um, 2500 kg/m^3: the tiny models are trained for others
    with pytest.raises(ConfigError, match="trained for"):
        check_model(model, flow.species_list)
    assert check_model(model, flow.species_list, force=True)  # --force lets the user take it anyway


SCRIPT = ROOT / "cases" / "tutorial_classifier.py"


def run(tmp_path, *args):
    done = subprocess.run([sys.executable, str(SCRIPT), "--no-progress", "--no-vtk", "--json", *args],
                          capture_output=True, text=True, cwd=ROOT, timeout=600)
    return done


def last_particles(out: Path):
    import zarr

    snaps = zarr.open_group(str(out / "run.zarr"), mode="r")["snapshots"]
    last = snaps[sorted(snaps.group_keys())[-1]]
    return last.attrs["time"], np.asarray(last["x"][...]), np.asarray(last["v"][...])


def test_resume_continues_bit_for_bit_and_the_shared_options_act(tmp_path):
    whole, part = tmp_path / "whole", tmp_path / "part"
    done = run(tmp_path, "--end-time", "0.02", "--output-interval", "0.005", "--out", str(whole))
    assert done.returncode == 0, done.stderr[-1500:]
    done = run(tmp_path, "--end-time", "0.01", "--output-interval", "0.005", "--checkpoint-interval", "0.005",
               "--out", str(part))
    assert done.returncode == 0, done.stderr[-1500:]
    # an existing run directory is refused without --overwrite or --resume, nothing touched
    again = run(tmp_path, "--end-time", "0.02", "--out", str(part))
    assert again.returncode == 2 and again.stderr.strip().startswith("hel-warp: error:")
    done = run(tmp_path, "--end-time", "0.02", "--output-interval", "0.005", "--resume", "--out", str(part))
    assert done.returncode == 0, done.stderr[-1500:]
    summary = json.loads(done.stdout.strip().splitlines()[-1])
    assert summary["status"] == "complete"
    t1, x1, v1 = last_particles(whole)
    t2, x2, v2 = last_particles(part)
    assert t1 == pytest.approx(0.02) and t2 == pytest.approx(0.02)
    np.testing.assert_array_equal(x1, x2)
    np.testing.assert_array_equal(v1, v2)


def test_members_that_start_together_build_the_automatic_model_once(tmp_path, monkeypatch):
    """Two runs asking at once for the same automatic surrogate (an ensemble's first members): one builds it, the
    other waits on the cache's lock and then uses it, instead of both writing into one folder."""
    import threading
    import time

    from hel_warp.case import models

    monkeypatch.setenv("HEL_WARP_CACHE", str(tmp_path))
    builds = []

    def slow_build(species, form, root, model_dir, announce):
        builds.append(threading.get_ident())
        time.sleep(0.5)
        model_dir.mkdir(parents=True)
        write_constant_contact_forest(model_dir)
        (model_dir / "metadata.json").write_text("{}")
        return str(model_dir)

    monkeypatch.setattr(models, "_build_model", slow_build)
    species = [hc.Species(name="glass", diameter=315e-6)]
    got = []
    threads = [threading.Thread(target=lambda: got.append(models.model_for(species, announce=lambda *_: None)))
               for _ in range(2)]
    for t in threads:
        t.start()
    for t in threads:
        t.join()
    assert len(builds) == 1
    assert len(got) == 2 and got[0] == got[1]


def test_a_cached_automatic_model_that_no_longer_loads_is_set_aside_and_built_again(tmp_path, monkeypatch):
    """An automatic surrogate in the cache whose forest.json no longer matches the sha256 its metadata recorded
    (edited or damaged after it was built) is moved aside, kept for inspection, and built again with a warning,
    instead of every run that needs it stopping on the checksum error."""
    from hel_warp.case import models
    from hel_warp.collisions.forest import sha256_file

    monkeypatch.setenv("HEL_WARP_CACHE", str(tmp_path))
    builds = []

    def build(species, form, root, model_dir, announce):
        builds.append(1)
        model_dir.mkdir(parents=True)
        write_constant_contact_forest(model_dir)
        files = {"forest.json": sha256_file(model_dir / "forest.json")}
        (model_dir / "metadata.json").write_text(json.dumps({"files": files}))
        return str(model_dir)

    monkeypatch.setattr(models, "_build_model", build)
    species = [hc.Species(name="glass", diameter=315e-6)]
    said = []
    first = models.model_for(species, announce=said.append)
    assert models.model_for(species, announce=said.append) == first and len(builds) == 1 and not said
    forest = Path(first) / "forest.json"
    forest.write_text(forest.read_text().replace('"max_depth": 0', '"max_depth":  0'))  # same JSON, other bytes
    again = models.model_for(species, announce=said.append)
    assert again == first and len(builds) == 2
    assert len(said) == 1 and "no longer loads" in said[0]
    aside = [p for p in Path(first).parent.iterdir() if p.name.startswith("model.unreadable-")]
    assert len(aside) == 1 and (aside[0] / "forest.json").read_text() != forest.read_text()


def test_no_pictures_skips_the_pictures_and_nothing_else(tmp_path):
    """``--no-pictures`` (a shared output option) leaves out the case's picture and keeps the same summary."""
    root = Path(__file__).resolve().parents[1]
    argv = [sys.executable, str(root / "cases" / "homogeneous_cooling.py"), "--collisions", "none",
            "--solids-fraction", "0.01", "--particles", "216", "--diameter", "315e-6", "--granular-temperature", "1",
            "--end-time", "3e-5", "--dt", "1e-5", "--json", "--no-progress", "--no-vtk"]
    out = {}
    for name, extra in (("with", []), ("without", ["--no-pictures"])):
        done = subprocess.run(argv + extra + ["--out", str(tmp_path / name)], capture_output=True, text=True)
        assert done.returncode == 0, done.stderr[-2000:]
        out[name] = json.loads(done.stdout.strip().splitlines()[-1])
    assert (tmp_path / "with" / "cooling.png").exists()
    assert not (tmp_path / "without" / "cooling.png").exists()
    keep = ("granular_temperature_final", "collisions", "steps")
    assert {k: out["with"][k] for k in keep} == {k: out["without"][k] for k in keep}


def test_a_pressure_plane_is_exact_for_a_linear_field_up_to_the_boundary_faces():
    """A pressure linear along z, p = a + b z at the cell centres, with a solid column: the plane probe gives
    a + b z at a cell centre, between two centres and on the boundary faces (the distributor at z = 0, the outlet
    at the top: the line extended over the half cell), and a drop between the faces of b times the height; a
    position outside the domain is refused in one line."""
    from types import SimpleNamespace

    from hel_warp.case.probes import Pressure, PressureDrop

    shape, h = (3, 2, 5), 2e-3
    fluid = np.ones(shape, np.int32)
    fluid[0, 0, :] = 0  # a solid column: its pressure (garbage here) must not enter the means
    z = (np.arange(shape[2]) + 0.5) * h
    a, b = 101.5, -2.5e3
    p = np.broadcast_to(a + b * z, shape).astype(np.float32).copy()
    p[0, 0, :] = 1e9

    class Arr:
        def __init__(self, v):
            self.v = v

        def numpy(self):
            return self.v

    sim = SimpleNamespace(grid=SimpleNamespace(origin=(0.0, 0.0, 0.0), spacing=h, shape=shape),
                          solver=SimpleNamespace(cell_fluid=Arr(fluid), gas=SimpleNamespace(cell_pressure=Arr(p))))
    flow = SimpleNamespace(lo=(0.0, 0.0, 0.0), hi=tuple(n * h for n in shape), spacing=h, grid_shape=shape)
    for position in (0.0, 0.5 * h, 0.3 * h, 1.7 * h, 2.5 * h, 4.9 * h, 5 * h):
        probe = Pressure(name="p", axis="z", position=position)
        probe.check(flow)
        probe.bind(sim)
        assert probe.sample(sim)["pressure"] == pytest.approx(a + b * position, rel=1e-6, abs=1e-6 * abs(b) * h)
    drop = PressureDrop(name="d", axis="z", low=0.0, high=5 * h)
    drop.check(flow)
    drop.bind(sim)
    assert drop.sample(sim)["pressure_drop"] == pytest.approx(-b * 5 * h, rel=1e-5)
    with pytest.raises(ConfigError, match="outside the domain"):
        Pressure(name="p", axis="z", position=5.2 * h).check(flow)
