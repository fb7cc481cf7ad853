"""A point cloud that shows part of the body (one scanner's view): the one-way loss
(``ChamferLoss(coverage="partial")``, ``warp-esph fit --cloud-coverage partial``) and the
warning a two-way loss gives such a cloud. Judged in float64 against central differences
and against the run that made the scan."""

import warnings

import numpy as np
import pytest
import warp as wp

import warp_esph as we
from warp_esph.fit import fit
from warp_esph.losses import ChamferLoss, surface_particles
from warp_esph.rollout import Rollout

from taped_loss import loss_central_differences

NOISE = 2e-4  # a lab scanner's 0.2 mm


def _cylinder(yield_stress, radius=0.03, height=0.08, speed=2.0):
    """A soft plastic cylinder (2 cm spacing; 36 particles at the defaults) hitting the
    ground, float64, the lattice jittered by 1e-3 spacings."""
    b = we.SceneBuilder(spacing=0.02)
    b.add_cylinder((0.0, 0.5 * height + 0.005, 0.0), radius, height, we.Material(
        mu=2e3, lam=3e3, density=1000.0, yield_stress=yield_stress, flow_rate=10.0), velocity=(0.0, -speed, 0.0))
    b.add_ground(friction=0.5)
    model = b.finalize(dtype=wp.float64, requires_grad=True)
    model.particle_x0 += np.random.default_rng(5).normal(scale=1e-3 * 0.02, size=model.particle_x0.shape)
    model.compute_rest_density()
    return model


def _top_half(x, noise=0.0, seed=0):
    """The points of ``x`` above the middle of its height, as a scanner above sees them."""
    mid = 0.5 * (x[:, 1].min() + x[:, 1].max())
    top = x[x[:, 1] > mid]
    return top + np.random.default_rng(seed).normal(scale=noise, size=top.shape)


def _brute_one_way(x, y, r):
    d2 = ((x[:, None, :] - y[None, :, :]) ** 2).sum(-1)
    return np.minimum(d2.min(axis=0), r * r).mean()


def test_the_one_way_loss_is_the_scans_mean_squared_distance_and_its_gradient_is_exact():
    """``coverage="partial"``: the mean over the cloud's points of the squared distance to
    the nearest particle (truncated at the radius), and its gradient in float64 against
    central differences, for a particle nearest to a scan point and for one no scan point
    sees (gradient 0: the unseen side is free)."""
    rng = np.random.default_rng(0)
    x = rng.uniform(-0.05, 0.05, size=(60, 3))
    y = x[x[:, 1] > 0.0][:20] + rng.normal(scale=0.003, size=(20, 3))
    y = np.concatenate([y, [[0.5, 0.5, 0.5]]])  # a stray point: nothing within the radius
    r = 0.02
    loss = ChamferLoss(y, radius=r, frames=[3], coverage="partial")
    pos = {3: wp.array(x, dtype=wp.vec3d)}
    value, grads = loss.value_and_grad(pos)
    assert value == pytest.approx(_brute_one_way(x, y, r), rel=1e-12, abs=0.0)
    assert loss.unmatched[3] == (0, 1)
    g = grads[3].numpy()
    d2 = ((x[:, None, :] - y[None, :, :]) ** 2).sum(-1)
    seen = np.unique(d2.argmin(axis=0)[d2.min(axis=0) < r * r])
    unseen = np.setdiff1d(np.arange(len(x)), seen)
    assert len(seen) > 5 and len(unseen) > 20
    assert np.all(g[unseen] == 0.0), "a particle no scan point is nearest to is not pulled"
    entries = [(int(i), c) for i in seen[:4] for c in range(3)] + [(int(unseen[0]), 1)]
    fd = loss_central_differences(loss, x, entries, 3, eps=1e-6)
    assert np.array([g[i, c] for i, c in entries]) == pytest.approx(np.array(fd), rel=1e-6, abs=0.0)
    r2 = loss.residuals({3: x})
    assert np.sum(r2**2) == pytest.approx(loss.residual_scale() * value, rel=1e-10, abs=0.0)
    with pytest.raises(ValueError, match="coverage = 'half' is not allowed: must be one of 'full', 'partial'"):
        ChamferLoss(y, radius=r, frames=[3], coverage="half")


def test_the_one_way_loss_differentiates_through_a_rollout():
    """d loss / d yield_stress through a landing, float64, against central differences."""
    truth = _cylinder(300.0)
    dt = 0.5 * truth.stable_dt()
    scan = _top_half(Rollout(truth, 80, dt, frames=[80]).forward()[-1])
    model = _cylinder(450.0)
    r = Rollout(model, 80, dt, frames=[80])
    loss = ChamferLoss(scan, radius=0.06, frames=[80], coverage="partial")
    from taped_loss import rollout_central_difference  # noqa: PLC0415

    tape, fd = rollout_central_difference(r, loss, "yield_stress")
    assert abs(fd) > 1e-12
    assert tape == pytest.approx(fd, rel=1e-4)


def test_a_top_half_scan_of_the_true_shape_scores_at_the_noise_with_the_one_way_loss():
    """A 0.2 mm scan of the top half of the shape the run made: the one-way loss is the
    scan's noise (3 sigma^2 = 1.2e-7 m^2 to sampling), the two-way loss far above it (the
    unseen bottom counted as misfit: 1.4e-4 m^2 measured on a 192-particle cylinder)."""
    truth = _cylinder(300.0)
    dt = 0.5 * truth.stable_dt()
    x = Rollout(truth, 80, dt, frames=[80]).forward()[-1]
    scan = _top_half(x, NOISE)
    pos = {80: wp.array(x, dtype=wp.vec3d)}
    one_way = ChamferLoss(scan, radius=0.06, frames=[80], coverage="partial").value(pos)
    two_way = ChamferLoss(scan, radius=0.06, frames=[80]).value(pos)
    assert one_way < 2.0 * 3 * NOISE**2
    assert two_way > 100.0 * 3 * NOISE**2


def test_a_fit_to_a_top_half_scan_recovers_the_yield_stress_with_the_one_way_loss():
    """From twice the yield stress, a fit to the top half of the true final shape finds it."""
    truth = _cylinder(300.0)
    dt = 0.5 * truth.stable_dt()
    scan = _top_half(Rollout(truth, 80, dt, frames=[80]).forward()[-1])
    loss = ChamferLoss(scan, radius=0.06, frames=[80], coverage="partial")
    with warnings.catch_warnings():
        warnings.simplefilter("error")  # no coverage warning for a one-way loss
        result = fit(_cylinder(600.0), loss, ["yield_stress"], steps=80, dt=dt, optimizer="lbfgs", iterations=15,
                     progress=False, diagnostics=False)
    assert result.params["yield_stress"][0] == pytest.approx(300.0, rel=0.02), [h["loss"] for h in result.history]


def test_a_two_way_loss_on_a_scan_of_part_of_the_body_is_warned_of():
    """The guess's run (126 particles) against a top-half scan, fitted two-way: the fit
    says that the cloud looks like part of the body and how to fit it; a full scan, a sparse
    full scan and the one-way loss are not warned of."""
    from warp_esph.losses import scan_coverage

    truth = _cylinder(300.0, radius=0.05, height=0.12, speed=1.0)
    dt = 0.5 * truth.stable_dt()
    x = Rollout(truth, 40, dt, frames=[40]).forward()[-1]
    surface = x[surface_particles(truth)]
    unseen, stray, _ = scan_coverage(surface, _top_half(x, NOISE), truth.spacing)
    assert unseen > 0.3 and stray == 0.0
    common = dict(steps=40, dt=dt, iterations=0, progress=False, diagnostics=False)
    with pytest.warns(UserWarning, match=r"target: the point cloud at step 40 looks like a scan of part of the body: "
                                         r"\d+% of the body's surface particles .* --cloud-coverage partial"):
        fit(_cylinder(600.0, 0.05, 0.12, 1.0), ChamferLoss(_top_half(x, NOISE), radius=0.06, frames=[40]),
            ["yield_stress"], **common)
    full = x + np.random.default_rng(1).normal(scale=NOISE, size=x.shape)
    with warnings.catch_warnings():
        warnings.simplefilter("error")
        for loss in (ChamferLoss(full, radius=0.06, frames=[40]), ChamferLoss(full[::4], radius=0.06, frames=[40]),
                     ChamferLoss(_top_half(x, NOISE), radius=0.06, frames=[40], coverage="partial")):
            fit(_cylinder(600.0, 0.05, 0.12, 1.0), loss, ["yield_stress"], **common)


def test_the_command_fits_a_scan_of_part_of_the_body_with_cloud_coverage_partial(tmp_path, capsys, dough_scene):
    """``warp-esph fit --cloud-coverage partial``: the top half of the last frame of the
    scene's own run (an 81-particle column) scores 0 (the one-way loss reached the command), where the default
    two-way loss scores the unseen bottom and warns, naming the option; the option is
    refused for a target that is no point cloud."""
    import json

    from warp_esph.cli import main
    from warp_esph.fit import load_target

    scene = tmp_path / "dough.toml"
    # A column (3 x 9 x 3 particles): a cube of 4 a side lands to 3 layers, all near its top half.
    scene.write_text(dough_scene(yield_stress=100.0, flow_rate=10.0, frames=2).replace(
        "center = [0.0, 0.045, 0.0]\nsize = [0.08, 0.08, 0.08]", "center = [0.0, 0.095, 0.0]\nsize = [0.06, 0.18, 0.06]"))
    assert "size = [0.06, 0.18, 0.06]" in scene.read_text()
    run = tmp_path / "run.usdc"
    assert main(["run", str(scene), "-o", str(run), "--dtype", "float64", "--no-progress"]) == 0
    np.savetxt(tmp_path / "top.xyz", _top_half(load_target(run, frames="last").data[0]))
    fit = ["fit", str(scene), "--target", str(tmp_path / "top.xyz"), "--params", "yield_stress", "--iterations", "0",
           "--no-usd", "--no-progress", "--no-diagnostics"]
    losses = {}
    for coverage in ("full", "partial"):
        capsys.readouterr()
        extra = [] if coverage == "full" else ["--cloud-coverage", "partial"]
        assert main([*fit, *extra, "--output-dir", str(tmp_path / coverage)]) == 0
        losses[coverage] = json.loads((tmp_path / coverage / "fit.json").read_text())["loss"]
        said = capsys.readouterr().err
        assert ("looks like a scan of part of the body" in said) == (coverage == "full"), said
        assert ("--cloud-coverage partial" in said) == (coverage == "full"), said
    assert losses["partial"] < 1e-20 < 1e-6 < losses["full"], losses
    assert main(["fit", str(scene), "--target", str(run), "--no-progress", "--iterations", "0", "--cloud-coverage",
                 "partial"]) == 2
    assert "--cloud-coverage = 'partial' is not allowed: it is how much of the body point-cloud targets show, and the " \
           "targets are positions" in capsys.readouterr().err


def test_the_command_takes_a_cloud_coverage_per_target(tmp_path, capsys, dough_scene):
    """Two clouds of the scene's own last frame, its top half and the whole of it: given
    ``--cloud-coverage partial --cloud-coverage full`` (one per ``--target``, in order) the fit
    scores both 0, where the option was global and the last one given, full, scored the top
    half's unseen bottom; so does an ``--experiments`` entry's ``cloud_coverage`` list. A count
    that is neither one nor one per target, and partial for a target that is no cloud, are
    refused naming the option."""
    import json

    from warp_esph.cli import main
    from warp_esph.fit import load_target

    scene = tmp_path / "dough.toml"
    scene.write_text(dough_scene(yield_stress=100.0, flow_rate=10.0, frames=2).replace(
        "center = [0.0, 0.045, 0.0]\nsize = [0.08, 0.08, 0.08]", "center = [0.0, 0.095, 0.0]\nsize = [0.06, 0.18, 0.06]"))
    run = tmp_path / "run.usdc"
    assert main(["run", str(scene), "-o", str(run), "--dtype", "float64", "--no-progress"]) == 0
    last = load_target(run, frames="last").data[0]
    np.savetxt(tmp_path / "top.xyz", _top_half(last))
    np.savetxt(tmp_path / "all.xyz", last)
    fit = ["fit", str(scene), "--params", "yield_stress", "--iterations", "0", "--no-usd", "--no-progress",
           "--no-diagnostics", "--target", str(tmp_path / "top.xyz"), "--target", str(tmp_path / "all.xyz")]
    losses = {}
    for name, extra in (("each", ["--cloud-coverage", "partial", "--cloud-coverage", "full"]),
                        ("full", ["--cloud-coverage", "full"])):
        assert main([*fit, *extra, "--output-dir", str(tmp_path / name)]) == 0, capsys.readouterr().err
        losses[name] = json.loads((tmp_path / name / "fit.json").read_text())["loss"]
    assert losses["each"] < 1e-20 < 1e-6 < losses["full"], losses
    # Copies: one file observed by both experiments would count its observations twice (refused).
    np.savetxt(tmp_path / "top2.xyz", _top_half(last))
    np.savetxt(tmp_path / "all2.xyz", last)
    (tmp_path / "exp.json").write_text(json.dumps([{"scene": str(scene), "target": ["top2.xyz", "all2.xyz"],
                                                    "cloud_coverage": ["partial", "full"]}]))
    assert main([*fit, "--cloud-coverage", "partial", "--cloud-coverage", "full", "--experiments",
                 str(tmp_path / "exp.json"), "--output-dir", str(tmp_path / "exp")]) == 0, capsys.readouterr().err
    losses["experiments"] = json.loads((tmp_path / "exp" / "fit.json").read_text())["loss"]
    assert losses["experiments"] < 1e-20, losses
    capsys.readouterr()
    assert main([*fit, *["--cloud-coverage", "partial"] * 3]) == 2
    assert "--cloud-coverage is given 3 times for 2 --target files: give it once per --target" in capsys.readouterr().err
    assert main([*fit[:-4], "--target", str(run), "--target", str(tmp_path / "top.xyz"), "--cloud-coverage", "partial",
                 "--cloud-coverage", "partial"]) == 2
    assert f"--cloud-coverage #1 = 'partial' is not allowed: the target {run} is particle positions, compared one to " \
           "one, not a point cloud; give full for it" in capsys.readouterr().err


def test_a_target_that_is_no_point_cloud_refuses_partial_coverage_a_mesh_saying_why(tmp_path):
    """``Target.loss(coverage="partial")`` of a mesh target built its ``MeshLoss`` and dropped
    the coverage without a word: a mesh target is closed (``load_mesh`` refuses an open one),
    so it shows the whole body, and the refusal says to fit a scan of part of the body as a
    cloud. Particle positions refuse it too; the mesh's own vertices as a cloud take it."""
    from warp_esph.fit import load_target
    from warp_esph.meshes import write_mesh

    model = _cylinder(300.0)
    corners = np.array([[i, j, k] for i in (-1, 1) for j in (-1, 1) for k in (-1, 1)], float) * 0.03
    quads = [(0, 1, 3, 2), (4, 6, 7, 5), (0, 4, 5, 1), (2, 3, 7, 6), (0, 2, 6, 4), (1, 5, 7, 3)]
    write_mesh(tmp_path / "box.obj", corners + [0.0, 0.04, 0.0], [t for a, b, c, d in quads for t in ((a, b, c), (a, c, d))])
    mesh = load_target(tmp_path / "box.obj")
    assert mesh.kind == "mesh"
    with pytest.raises(ValueError, match=r"coverage \(--cloud-coverage\) = 'partial' is not allowed: the target .*box\.obj "
                                         r"is a mesh, not a point cloud; a mesh target is closed .* fit a scan of part of "
                                         r"the body as a point cloud of its points; give full for it"):
        mesh.loss(model, {1: 10}, coverage="partial")
    with pytest.raises(ValueError, match="coverage = 'half' is not allowed: must be one of 'full', 'partial'"):
        mesh.loss(model, {1: 10}, coverage="half")
    assert type(mesh.loss(model, {1: 10})).__name__ == "MeshLoss"
    np.save(tmp_path / "x.npy", model.particle_x0)
    with pytest.raises(ValueError, match="is particle positions, compared one to one, not a point cloud"):
        load_target(tmp_path / "x.npy").loss(model, {1: 10}, coverage="partial")
    np.savetxt(tmp_path / "corners.xyz", corners + [0.0, 0.04, 0.0])
    cloud = load_target(tmp_path / "corners.xyz").loss(model, {1: 10}, coverage="partial")
    assert isinstance(cloud, ChamferLoss) and cloud.coverage == "partial"


def _block_on_floor(yield_stress, worlds=1):
    """A 3 x 5 x 3 column (2 cm spacing) on a plastic particle floor of its own material
    (two pinned layers, two spacings beyond its footprint), float64."""
    b = we.SceneBuilder(spacing=0.02)
    b.add_box((0.0, 0.07, 0.0), (0.06, 0.10, 0.06), we.Material(
        mu=2e3, lam=3e3, density=1000.0, yield_stress=yield_stress, flow_rate=10.0), name="block")
    b.add_particle_floor("block", margin=0.04)
    return b.finalize(dtype=wp.float64, requires_grad=True, worlds=worlds)


def test_a_full_scan_of_a_sample_on_a_particle_floor_is_not_taken_for_part_of_it():
    """The floor's particles are the block's body and pinned: a full scan of the block's
    final shape (no floor in it) left the floor's surface unseen and was warned of as a
    scan of part of the body (59 % unseen). Pinned particles are held, not unseen: the full
    scan passes, and a scan of the block's top half is still warned of."""
    truth = _block_on_floor(300.0)
    dt = 0.5 * truth.stable_dt()
    x = Rollout(truth, 20, dt, frames=[20]).forward()[-1]
    pinned = truth.tools.pin.numpy() >= 0
    assert 0 < pinned.sum() < len(x)
    block = x[~pinned]
    common = dict(steps=20, dt=dt, iterations=0, progress=False, diagnostics=False)
    with warnings.catch_warnings():
        warnings.simplefilter("error")
        fit(_block_on_floor(600.0), ChamferLoss(block, radius=0.06, frames=[20]), ["yield_stress"], **common)
    with pytest.warns(UserWarning, match="target: the point cloud at step 20 looks like a scan of part of the body"):
        fit(_block_on_floor(600.0), ChamferLoss(_top_half(block), radius=0.06, frames=[20]), ["yield_stress"], **common)


def test_a_scan_of_part_of_the_body_in_a_world_loss_is_warned_of_naming_its_world():
    """A ``WorldLoss`` of two worlds, world 0 with a full scan and world 1 with a top-half
    scan of the same run, both two-way: the fit warns of world 1's cloud alone."""
    from warp_esph.losses import WorldLoss

    truth = _cylinder(300.0, radius=0.05, height=0.12, speed=1.0)
    dt = 0.5 * truth.stable_dt()
    x = Rollout(truth, 40, dt, frames=[40]).forward()[-1]
    b = we.SceneBuilder(spacing=0.02)
    b.add_cylinder((0.0, 0.065, 0.0), 0.05, 0.12, we.Material(mu=2e3, lam=3e3, density=1000.0, yield_stress=600.0,
                                                              flow_rate=10.0), velocity=(0.0, -1.0, 0.0))
    b.add_ground(friction=0.5)
    worlds = b.finalize(dtype=wp.float64, requires_grad=True, worlds=2)
    assert worlds.world_start[1] == len(x)
    loss = WorldLoss(worlds, [ChamferLoss(x, radius=0.06, frames=[40]), ChamferLoss(_top_half(x), radius=0.06, frames=[40])])
    with pytest.warns(UserWarning) as record:
        fit(worlds, loss, ["yield_stress"], steps=40, dt=dt, iterations=0, progress=False, diagnostics=False)
    said = [str(w.message) for w in record if "scan of part of the body" in str(w.message)]
    assert len(said) == 1 and said[0].startswith("target (world 1): the point cloud at step 40"), said


def _box_world(size):
    """A box of ``size`` (m) on the ground at 2 cm spacing."""
    b = we.SceneBuilder(spacing=0.02)
    b.add_box((0.0, 0.5 * size[1] + 0.01, 0.0), size, we.Material(mu=2e3, lam=3e3, density=1000.0))
    return b


def test_one_cloud_loss_shared_by_two_worlds_keeps_each_world_s_records_and_check():
    """One ``ChamferLoss`` given for every world of a ``WorldLoss``: each world's copy keeps
    its own ``unmatched`` and its own partial-scan check. Two bodies of 18 particles each, a
    3 x 2 x 3 block and a 3 x 6 x 1 wall; a cloud of the block shows only the bottom of
    the wall: the wall's world is warned for, and each world's ``unmatched`` and value are
    what the loss alone gives on that world's positions (the copies shared one dict, and
    one set of checked frames: the block's check marked the frame done and the wall was
    never checked)."""
    from warp_esph.builder import finalize_worlds
    from warp_esph.losses import WorldLoss

    model = finalize_worlds([_box_world((0.06, 0.04, 0.06)), _box_world((0.06, 0.12, 0.02))], dtype=wp.float64)
    x = model.particle_x0.astype(np.float64)
    starts = model.world_start
    block, wall = x[starts[0]:starts[1]], x[starts[1]:starts[2]]
    assert len(block) == len(wall) == 18
    cloud = block + np.array([0.0, 0.0, 1e-3])  # the block as scanned (no point on a particle)
    r = 0.05

    def alone(xw):
        loss = ChamferLoss({1: cloud}, radius=r)
        value = loss.value({1: wp.array(xw, dtype=wp.vec3d)})
        return value, loss.unmatched[1]

    shared = ChamferLoss({1: cloud}, radius=r)
    # Every particle of both bodies is on its surface: 0..17 of each world's positions.
    shared.watch_coverage(np.arange(18), model.spacing, "target")
    worlds = WorldLoss(model, shared)
    with warnings.catch_warnings(record=True) as rec:
        warnings.simplefilter("always")
        worlds.value({1: wp.array(x, dtype=wp.vec3d)})
    partial = [str(w.message) for w in rec if "scan of part of the body" in str(w.message)]
    assert len(partial) == 1, partial
    assert "50% of the body's surface particles" in partial[0], partial[0]  # the wall's upper 3 rows

    v_block, u_block = alone(block)
    v_wall, u_wall = alone(wall)
    assert u_block[0] == 0 and u_wall[0] > 0, (u_block, u_wall)
    assert [loss.unmatched[1] for loss in worlds.losses] == [u_block, u_wall]
    assert worlds.world_values == pytest.approx([v_block, v_wall], rel=1e-12, abs=0.0)


def test_one_mesh_loss_shared_by_two_worlds_counts_each_world_s_unmatched_particles():
    """``MeshLoss.unmatched`` of a ``WorldLoss``'s worlds: one loss given for every world,
    each world's copy counts its own world's particles beyond ``max_dist`` (the copies
    shared one dict, and every world read the last world's count)."""
    from warp_esph.builder import finalize_worlds
    from warp_esph.losses import MeshLoss, WorldLoss

    model = finalize_worlds([_box_world((0.06, 0.04, 0.06)), _box_world((0.06, 0.12, 0.02))], dtype=wp.float64)
    x = model.particle_x0.astype(np.float64)
    starts = model.world_start
    # One large triangle in the plane y = 0.02: the block lies within max_dist of it, the
    # wall's upper rows beyond.
    mesh = (np.array([[-1.0, 0.02, -1.0], [1.0, 0.02, -1.0], [0.0, 0.02, 1.0]]), np.array([[0, 1, 2]]))

    def alone(xw):
        loss = MeshLoss(mesh, frames=[1], max_dist=0.03)
        loss.value({1: wp.array(xw, dtype=wp.vec3d)})
        return loss.unmatched[1]

    worlds = WorldLoss(model, MeshLoss(mesh, frames=[1], max_dist=0.03))
    worlds.value({1: wp.array(x, dtype=wp.vec3d)})
    expected = [alone(x[starts[w]:starts[w + 1]]) for w in range(2)]
    assert expected[0] == 0 and expected[1] > 0, expected
    assert [loss.unmatched[1] for loss in worlds.losses] == expected
