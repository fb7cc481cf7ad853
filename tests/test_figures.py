"""The paper's figures as built-in scenes: Table 1 particle counts and steps, and short runs."""

import math

import numpy as np
import pytest

import warp_esph as we
from warp_esph.cli import main
from warp_esph.scenes import FIG8_PLASTIC_MIN_SCALE, FIGURE_SCENES, SCENES, TABLE1, get_scene, paper_run_scene
from warp_esph.simulate import resolve_timestep, simulate

#: A scale per figure scene giving a few hundred particles (a coarse but complete scene).
SMALL = {
    "fig1_non_newtonian": 0.2,
    "fig2_three_cylinders": 0.2,
    "fig3_pile": 0.45,
    "fig4_bunny_on_sphere": 0.2,
    "fig5_hyperelastic_boxes": 0.6,
    "fig6_dough_star": 0.3,
    "fig7_plastic_grid": 0.15,
    # Its very plastic cubes are refused below 0.6 (they come apart; scenes.FIG8_PLASTIC_MIN_SCALE).
    "fig8_comparison": 0.6,
}


def test_every_figure_has_a_scene():
    assert set(SMALL) == set(FIGURE_SCENES)
    figures = sorted(get_scene(n, SMALL[n]).figure for n in FIGURE_SCENES)
    assert figures == [f"Fig. {k}" for k in range(1, 9)]
    assert list(SCENES)[0] == "dough_drop"  # still the default, first in the list


@pytest.mark.parametrize("run", TABLE1, ids=lambda r: r.label)
def test_table1_particle_count_and_step_at_scale_1(run):
    scene = paper_run_scene(run)
    n = scene.builder.particle_count
    assert abs(n - run.particles) <= 0.05 * run.particles, f"{run.label}: {n} particles, paper {run.particles}"
    assert [b.name for b in scene.builder._bodies] == list(run.bodies)
    assert scene.dt == pytest.approx(run.dt, rel=1e-12, abs=0.0)
    # The paper's step divides a frame exactly (25 fps).
    model_free_steps = (1.0 / scene.fps) / scene.dt
    assert model_free_steps == pytest.approx(round(model_free_steps), abs=1e-6)


@pytest.mark.parametrize("name", FIGURE_SCENES)
def test_scale_keeps_the_courant_number(name):
    # Fig. 8 refuses its very plastic cubes below 0.6 (scenes.FIG8_PLASTIC_MIN_SCALE).
    scale = FIG8_PLASTIC_MIN_SCALE if name == "fig8_comparison" else 0.5
    full, small = get_scene(name).dt, get_scene(name, scale=scale).dt
    assert small == pytest.approx(full / scale, rel=0.02)  # dt follows the spacing, rounded to whole steps
    assert small <= full / scale * (1 + 1e-12)
    frame = 1.0 / get_scene(name, scale).fps
    assert frame / small == pytest.approx(round(frame / small), abs=1e-6)


@pytest.mark.parametrize("name", FIGURE_SCENES)
def test_figure_scene_runs_small_without_nan(name):
    scene = get_scene(name, scale=SMALL[name])
    model = scene.builder.finalize()
    assert 100 <= model.particle_count <= 1500
    assert model.stable_dt() >= scene.dt * (1 - 1e-9), "the scene's step is above the stable step"
    substeps, dt = resolve_timestep(model, scene.fps, dt=scene.dt)
    state = simulate(model, 3, fps=scene.fps, dt=scene.dt, progress=False)
    x, v = state.x.numpy(), state.v.numpy()
    assert np.isfinite(x).all() and np.isfinite(v).all()
    assert not np.array_equal(x, model.particle_x0)
    # Nothing fell through the ground (small penetration allowed for the contact response).
    assert x[:, 1].min() > -model.spacing
    assert np.abs(v).max() < 20.0


def test_only_picks_the_bodies_of_one_run():
    scene = get_scene("fig7_plastic_grid", scale=0.15)
    assert len(scene.builder._bodies) == 6
    one = SCENES["fig7_plastic_grid"](scale=0.15, only=("flow_fast",))
    assert [b.name for b in one.builder._bodies] == ["flow_fast"]
    assert len(one.builder.planes) == 1
    with pytest.raises(ValueError, match="no body"):
        SCENES["fig2_three_cylinders"](scale=0.2, only=("rubber",))


def test_stable_at_the_paper_step_at_scale_1():
    """The paper's step is within ``Model.stable_dt`` (the wave, viscous and hourglass limits,
    with the solver the scene runs) of every figure scene at full resolution. Measured: 0.16 x
    (fig8_comparison) to 0.74 x (fig1_non_newtonian) of it."""
    for name in FIGURE_SCENES:
        scene = get_scene(name)
        model = scene.builder.finalize()
        solver = we.Solver(model)
        assert model.stable_dt(hourglass=solver.hourglass) >= scene.dt * (1 - 1e-9), name
        assert math.isclose(scene.fps, 25.0)


def test_cli_lists_and_runs_a_figure(tmp_path, capsys):
    assert main(["scenes"]) == 0
    out = capsys.readouterr().out
    for name in FIGURE_SCENES:
        assert any(line.startswith(name) and "Fig." in line for line in out.splitlines()), name
    path = tmp_path / "fig5.usdc"
    assert main(["run", "fig5_hyperelastic_boxes", "--scale", "0.5", "--frames", "1", "--no-progress", "-o", str(path),
                 "--preview"]) == 0
    out = capsys.readouterr().out
    assert "dt = 0.0002 s" in out and (tmp_path / "fig5.usdc.png").exists() and "preview:" in out
