"""The fleet file (agents/spec.py) for the autogrid fleet: no grid or sigma yet, frames of
max_points + 2 numbers, parameters filtered through AutoGridParams, a JSON round trip."""

from __future__ import annotations

import dataclasses
import json

import numpy as np
import pytest

from agents.autogrid import AdaptiveGridCore, AutoGridParams
from agents.certificate import PAYLOAD
from agents.soft_endgame import payload_size
from agents.spec import ALGORITHMS, FleetSpec, build_core

from .conftest import make_run


@pytest.fixture(scope="module")
def auto():
    return make_run(algorithm="autogrid", max_grid_points=60)


def test_autogrid_fleet_file_has_no_grid_and_no_sigma(auto):
    world, spec, central = auto
    assert "autogrid" in ALGORITHMS and spec.algorithm == "autogrid" and central is None
    assert spec.sigma is None and spec.grid.shape == (0, 2) and world.grid.shape == (0, 2)
    # a complete graph: the ADMM sub-machines' frames carry the hub's w beside v (agents/admm.py)
    assert spec.autogrid_params.hub_frames
    assert spec.dim == AutoGridParams(max_points=60, hub_frames=True).dim >= 2 * (60 + 1) + 2  # every vector fits
    assert spec.params["max_points"] == 60 and "max_rounds" not in spec.params
    with pytest.raises(ValueError, match="chooses its own grid"):
        spec.basis  # noqa: B018 -- there is no fixed basis to measure against


def test_json_round_trip_keeps_sigma_none_and_the_tag(auto, tmp_path):
    _, spec, _ = auto
    spec.save(tmp_path / "fleet.json")
    assert json.loads((tmp_path / "fleet.json").read_text())["sigma"] is None
    back = FleetSpec.load(tmp_path / "fleet.json")
    assert back.sigma is None and back.grid.shape == (0, 2) and back.dim == spec.dim
    assert back.config_tag == spec.config_tag
    assert spec.for_robot(1).config_tag == spec.config_tag  # a robot host's own file agrees
    fixed = dataclasses.replace(spec, sigma=0.5)
    assert fixed.config_tag != spec.config_tag  # a fixed sigma is another problem


def test_build_core_gives_each_robot_its_raw_points_and_the_shared_params(auto):
    _, spec, _ = auto
    core = build_core(spec, 1)
    assert isinstance(core, AdaptiveGridCore) and core.dim == spec.dim and core.trace == {}
    assert core.params == spec.autogrid_params
    assert (core.params.max_points, core.params.sigma, core.params.C) == (60, None, None)
    assert core.params.rho == spec.params["rho"] and core.params.diameter == spec.params["diameter"]


def test_params_are_autogrids_own_and_max_rounds_is_the_total_cap(auto):
    _, spec, _ = auto
    other = dataclasses.replace(spec, sigma=0.7, C=5.0, params={**spec.params, "model": "svm", "max_total_rounds": 1234})  # (C: the SVM model's)
    p = other.autogrid_params
    assert (p.max_total_rounds, p.sigma, p.C) == (1234, 0.7, 5.0)
    for key in ("max_rounds", "ct_step", "gamma_penalty_x"):  # keys of other algorithms or typos: refused by name
        bad = dataclasses.replace(spec, params={**spec.params, key: 1})
        with pytest.raises(ValueError, match=f"unknown autogrid parameter '{key}'"):
            bad.autogrid_params  # noqa: B018
    # the CLI's --max-rounds reaches autogrid as its total cap
    _, capped, _ = make_run(algorithm="autogrid", max_grid_points=60, max_rounds=4321)
    assert capped.autogrid_params.max_total_rounds == 4321


def test_start_grid_and_fixed_sigma():
    world, spec, _ = make_run(algorithm="autogrid", grid="4x2", sigma=1.0, max_grid_points=60)
    assert spec.sigma == 1.0 and len(spec.grid) == 8 and np.array_equal(world.grid, spec.grid)
    assert build_core(spec, 0).params.sigma == 1.0  # the start grid is used once sigma is agreed (test_cli Fig. 5)


def test_fixed_grid_algorithms_need_grid_and_sigma(auto):
    _, spec, _ = auto
    with pytest.raises(ValueError, match="admm needs a grid and a sigma"):
        dataclasses.replace(spec, algorithm="admm")
    _, paper, _ = make_run()
    # the paper's fleet is complete: the hub form's frames carry [v; w], 2 x (15 + 1) floats, and the exact
    # end-game's payload (agents/soft_endgame.py, the default on complete fleets); asking for the certified
    # guard, its 6 floats instead (agents/certificate.py)
    assert paper.algorithm == "admm" and paper.sigma == 1.0 and paper.dim == 32 + payload_size(16)
    paper.params["certify"] = 10.0
    assert paper.dim == 32 + PAYLOAD
    _, ring, _ = make_run(robots=4, topology="ring")
    # the relay hub sends a relayed a per robot and, with the certified guard (certify 10, the default),
    # its 6 certificate floats (agents/relay_hub.py) -- padded to the paused end-game's gather frame, 2
    # payloads of 70 floats (hard margins: agents/soft_endgame.py payload_size), where that is longer
    assert ring.dim == max(4 * (16 + PAYLOAD), 2 * payload_size(16)) == 140
    ring.params["relay"] = False
    assert ring.dim == 16  # the edge form sends v alone
