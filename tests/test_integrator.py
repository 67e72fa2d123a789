"""The admc_split integrator against Mitsuba's own `path` integrator, with real renders of tiny scenes."""

import numpy as np
import pytest

from admc.pipeline.render.integrator import INTEGRATOR_NAME, pass_seeds, register, render_buffers

SIZE = 32
BOX_FILM = {"type": "hdrfilm", "width": SIZE, "height": SIZE, "rfilter": {"type": "box"}}
# |z| above this on a 4x4-block statistic has a false-failure probability of ~1e-9 per block
# for a Gaussian; the admc variance used below is an upper bound, so H0 only gets safer.
Z_LIMIT = 6.0


def _cornell(mi):
    """Mitsuba's Cornell box (all diffuse) as a dict, on a tiny box-filtered film."""
    scene = mi.cornell_box()
    scene["sensor"]["film"] = dict(BOX_FILM)
    scene.pop("integrator")
    return scene


def _mixed_scene(mi):
    """Diffuse walls, rough plastic and rough conductor boxes, a glass ball and a tilted mirror."""
    T = mi.ScalarTransform4f
    scene = _cornell(mi)
    scene["plastic"] = {
        "type": "roughplastic",
        "alpha": 0.1,
        "diffuse_reflectance": {"type": "rgb", "value": [0.2, 0.3, 0.6]},
    }
    scene["metal"] = {"type": "roughconductor", "material": "Au", "alpha": 0.2}
    scene["large-box"]["bsdf"] = {"type": "ref", "id": "plastic"}
    scene["small-box"]["bsdf"] = {"type": "ref", "id": "metal"}
    scene["glass-ball"] = {
        "type": "sphere",
        "center": [0.45, 0.25, 0.35],
        "radius": 0.22,
        "bsdf": {"type": "dielectric"},
    }
    scene["mirror"] = {
        "type": "rectangle",
        "bsdf": {"type": "conductor"},
        "to_world": T().translate([0, 0.1, -0.95]).rotate([0, 1, 0], 25).scale([0.5, 0.5, 1]),
    }
    return mi.load_dict(scene)


def _glass_behind_mirror_scene(mi, wall_reflectance, mirror_reflectance):
    """Orthographic camera looking down -z at a 45-degree mirror that sends every ray along +x,
    through a glass slab, onto a diffuse wall at x = 5: each straight-through camera path is 10 long."""
    T = mi.ScalarTransform4f
    return mi.load_dict(
        {
            "type": "scene",
            "sensor": {
                "type": "orthographic",
                "film": dict(BOX_FILM),
                "to_world": T().look_at(origin=[0, 0, 5], target=[0, 0, 0], up=[0, 1, 0]),
            },
            "env": {"type": "constant", "radiance": {"type": "rgb", "value": 1.0}},
            "mirror": {
                "type": "rectangle",
                "bsdf": {"type": "conductor", "specular_reflectance": mirror_reflectance},
                "to_world": T().rotate([0, 1, 0], 45).scale(2.0),
            },
            "slab": {
                "type": "cube",
                "bsdf": {"type": "dielectric"},
                "to_world": T().translate([3, 0, 0]).scale([0.25, 3, 3]),
            },
            "wall": {
                "type": "rectangle",
                "bsdf": {"type": "diffuse", "reflectance": {"type": "rgb", "value": wall_reflectance}},
                "to_world": T().translate([5, 0, 0]).rotate([0, 1, 0], -90).scale(6.0),
            },
        }
    )


def _srgb_to_xyz_matrix(mi):
    return np.array([np.array(mi.srgb_to_xyz(mi.Color3f(*map(float, e)))).ravel() for e in np.eye(3)]).T


def _path_moments(mi, scene, spp, seed):
    """Mean and variance of the pixel mean of Mitsuba's `path`, both in XYZ (the `moment` integrator's units)."""
    moment = mi.load_dict({"type": "moment", "nested": {"type": "path", "max_depth": 8}})
    image = np.asarray(mi.render(scene, integrator=moment, spp=spp, seed=seed), dtype=np.float64)
    m1, m2 = image[..., -6:-3], image[..., -3:]
    return m1, np.maximum(m2 - m1**2, 0.0) / spp


def _block_sum(x, block=4):
    h, w, c = x.shape
    return x.reshape(h // block, block, w // block, block, c).sum(axis=(1, 3))


def _block_z(mi, rgb_mean, rgb_sd_bound, path_xyz, path_var):
    """z-scores of 4x4-block sums of the admc image minus the `path` image, per XYZ channel.

    The admc standard deviation passed in is an upper bound (sum of the parts' deviations), so
    the statistic is conservative under the null hypothesis and still sharp against bias.
    """
    m = _srgb_to_xyz_matrix(mi)
    xyz = rgb_mean.astype(np.float64) @ m.T
    var = (rgb_sd_bound.astype(np.float64) @ np.abs(m).T) ** 2
    return (_block_sum(xyz) - _block_sum(path_xyz)) / np.sqrt(_block_sum(var) + _block_sum(path_var) + 1e-12)


def test_register_is_idempotent_and_loadable(variant):
    import mitsuba as mi

    register()
    register()
    integrator = mi.load_dict({"type": INTEGRATOR_NAME, "max_depth": 5, "split": False})
    assert isinstance(integrator, mi.SamplingIntegrator)
    assert "specular.R" not in integrator.aov_names() and "diffuse.R" in integrator.aov_names()


def test_diffuse_plus_specular_matches_path_and_flags_wrong_sums(variant):
    """Independent seeds: block z-scores of (diffuse + specular) - path stay small, while the
    same statistic flags the specular part dropped or counted twice."""
    import mitsuba as mi

    scene = _mixed_scene(mi)
    spp = 512
    buf = render_buffers(scene, spp, seed=11)
    path_xyz, path_var = _path_moments(mi, scene, spp, seed=12345)
    sd_d, sd_s = np.sqrt(buf["diffuse_var"]), np.sqrt(buf["specular_var"])

    assert buf["specular"].sum() > 0.01 * buf["diffuse"].sum()
    z_right = _block_z(mi, buf["diffuse"] + buf["specular"], sd_d + sd_s, path_xyz, path_var)
    assert np.abs(z_right).max() < Z_LIMIT, np.abs(z_right).max()
    # The same statistic must see a dropped or double-counted specular part.
    z_dropped = _block_z(mi, buf["diffuse"], sd_d, path_xyz, path_var)
    z_doubled = _block_z(mi, buf["diffuse"] + 2 * buf["specular"], sd_d + 2 * sd_s, path_xyz, path_var)
    assert np.abs(z_dropped).max() > Z_LIMIT
    assert np.abs(z_doubled).max() > Z_LIMIT


@pytest.mark.parametrize("max_depth, rr_depth", [(0, 5), (1, 5), (3, 5), (8, 5), (8, 2)])
def test_same_seed_as_path_gives_the_same_image(variant, max_depth, rr_depth):
    """admc_split draws random numbers in `path`'s order, so one seed gives one image."""
    import mitsuba as mi

    register()
    scene = _mixed_scene(mi)
    params = {"max_depth": max_depth, "rr_depth": rr_depth}
    ours = np.asarray(mi.render(scene, integrator=mi.load_dict({"type": INTEGRATOR_NAME, **params}), spp=4, seed=5))
    theirs = np.asarray(mi.render(scene, integrator=mi.load_dict({"type": "path", **params}), spp=4, seed=5))
    np.testing.assert_allclose(ours[..., :3], theirs, rtol=1e-4, atol=1e-5)
    assert (theirs.max() > 0) == (max_depth > 0)


def test_albedo_of_rough_conductor_matches_monte_carlo(variant):
    """Orthographic view of a rough gold plane: every sample estimates the normal-incidence albedo."""
    import drjit as dr
    import mitsuba as mi

    T = mi.ScalarTransform4f
    bsdf_desc = {"type": "roughconductor", "material": "Au", "alpha": 0.3}
    scene = mi.load_dict(
        {
            "type": "scene",
            "sensor": {
                "type": "orthographic",
                "film": dict(BOX_FILM),
                "to_world": T().look_at(origin=[0, 0, 3], target=[0, 0, 0], up=[0, 1, 0]),
            },
            "env": {"type": "constant"},
            "plane": {"type": "rectangle", "bsdf": bsdf_desc, "to_world": T().scale(2.0)},
        }
    )
    buf = render_buffers(scene, 32, seed=3)
    albedo = buf["albedo"].reshape(-1, 3).mean(axis=0)

    # Independent estimate: integrate f*cos over the hemisphere with uniform directions.
    bsdf = mi.load_dict(bsdf_desc)
    n = 1 << 20
    rng = np.random.default_rng(0)
    si = dr.zeros(mi.SurfaceInteraction3f, n)
    si.wi = mi.Vector3f(0, 0, 1)
    si.sh_frame = mi.Frame3f(mi.Vector3f(0, 0, 1))
    uv = rng.random((2, n), dtype=np.float32)
    wo = mi.warp.square_to_uniform_hemisphere(mi.Point2f(uv[0], uv[1]))
    value = bsdf.eval(mi.BSDFContext(), si, wo) / mi.warp.square_to_uniform_hemisphere_pdf(wo)
    expected = np.array([dr.mean(value.x)[0], dr.mean(value.y)[0], dr.mean(value.z)[0]])

    assert np.all(albedo > 0.3)
    np.testing.assert_allclose(albedo, expected, rtol=0.02)
    # Under a white sky of radiance 1 the plane reflects exactly its albedo, all of it specular.
    np.testing.assert_array_equal(buf["diffuse"], 0.0)
    np.testing.assert_allclose(buf["specular"].reshape(-1, 3).mean(axis=0), expected, rtol=0.02)


def test_albedo_of_rough_plastic_is_its_diffuse_reflectance_in_every_sample(variant):
    """A rough plastic's BSDF sample weight depends on the lobe and direction drawn; its diffuse
    reflectance does not. The albedo must be the latter, exactly, in every pixel at 2 spp: dividing
    the diffuse buffer by a noisy albedo would add that noise to what the denoiser sees and returns."""
    import mitsuba as mi

    T = mi.ScalarTransform4f
    reflectance = [0.2, 0.3, 0.6]
    scene = mi.load_dict(
        {
            "type": "scene",
            "sensor": {
                "type": "orthographic",
                "film": dict(BOX_FILM),
                "to_world": T().look_at(origin=[0, 0, 3], target=[0, 0, 0], up=[0, 1, 0]),
            },
            "env": {"type": "constant"},
            "plane": {
                "type": "rectangle",
                "to_world": T().scale(2.0),
                "bsdf": {
                    "type": "twosided",
                    "bsdf": {
                        "type": "roughplastic",
                        "alpha": 0.3,
                        "diffuse_reflectance": {"type": "rgb", "value": reflectance},
                    },
                },
            },
        }
    )
    buf = render_buffers(scene, 2, seed=3)
    assert (buf["coverage"] == 1).all()
    np.testing.assert_allclose(buf["albedo"].reshape(-1, 3), np.broadcast_to(reflectance, (SIZE * SIZE, 3)), rtol=1e-6)
    assert buf["specular"].max() > 0  # the glossy lobe was sampled: the old sample-weight albedo varied here


def test_features_follow_mirror_and_glass_to_the_wall(variant):
    """Albedo, normal and depth are taken at the wall, behind a mirror and a glass slab.

    A sample crosses the slab with probability (1 - F) / (1 + F) (F: normal-incidence Fresnel
    reflectance of the default glass, all internal bounces summed) and gets albedo
    mirror * wall; otherwise the glass sends it back via the mirror into the sky: mirror^2 * 1.
    """
    import mitsuba as mi

    wall, mirror = 0.5, 0.8
    buf = render_buffers(_glass_behind_mirror_scene(mi, wall, mirror), 16, seed=1)
    covered = buf["coverage"][..., 0] > 0
    assert covered.all()
    for name in ("albedo", "normal", "depth", "coverage"):
        assert np.isfinite(buf[name]).all(), name
    fresnel = ((1.5046 - 1.000277) / (1.5046 + 1.000277)) ** 2  # Mitsuba's default bk7 / air
    crossing = (1 - fresnel) / (1 + fresnel)
    expected = crossing * mirror * wall + (1 - crossing) * mirror**2
    np.testing.assert_allclose(buf["albedo"].mean(), expected, atol=0.01)
    # Depth runs from the orthographic camera's near-clip plane (0.01): 9.99, a bit more for the
    # samples that bounced inside the slab before leaving it.
    depth = buf["depth"][covered]
    np.testing.assert_allclose(np.median(depth), 9.99, atol=0.005)
    assert depth.min() > 9.98 and depth.max() < 11.0
    normal = buf["normal"][covered] / buf["coverage"][covered]
    np.testing.assert_allclose(normal, np.broadcast_to([-1.0, 0.0, 0.0], normal.shape), atol=1e-3)


def test_split_false_has_no_specular_and_equals_path(variant):
    import mitsuba as mi

    scene = mi.load_dict(_cornell(mi))
    spp, seed = 16, 7
    buf = render_buffers(scene, spp, seed, split=False)
    assert set(buf) == {"diffuse", "diffuse_var", "albedo", "normal", "depth", "coverage"}
    np.testing.assert_array_equal(render_buffers(scene, spp, seed, split=True)["specular"], 0.0)
    path = mi.load_dict({"type": "path", "max_depth": 8})
    same_seed = np.asarray(mi.render(scene, integrator=path, spp=spp, seed=pass_seeds(seed, 1)[0]))
    np.testing.assert_allclose(buf["diffuse"], same_seed, rtol=1e-4, atol=1e-5)

    path_xyz, path_var = _path_moments(mi, scene, spp, seed=999)
    z = _block_z(mi, buf["diffuse"], np.sqrt(buf["diffuse_var"]), path_xyz, path_var)
    assert np.abs(z).max() < Z_LIMIT


def test_depth_and_normals_finite_where_only_environment_is_seen(variant):
    import mitsuba as mi

    T = mi.ScalarTransform4f
    scene = mi.load_dict(
        {
            "type": "scene",
            "sensor": {
                "type": "perspective",
                "fov": 40,
                "film": dict(BOX_FILM),
                "to_world": T().look_at(origin=[0, 0, 4], target=[0, 0, 0], up=[0, 1, 0]),
            },
            "env": {"type": "constant"},
            "ball": {"type": "sphere", "radius": 0.5, "bsdf": {"type": "roughplastic"}},
        }
    )
    buf = render_buffers(scene, 4, seed=0)
    for name, array in buf.items():
        assert np.isfinite(array).all(), name
    coverage = buf["coverage"][..., 0]
    sky = coverage == 0
    assert sky[0, 0] and sky.sum() > SIZE * SIZE // 2
    assert np.all(buf["depth"][sky] == 0) and np.all(buf["normal"][sky] == 0)
    assert np.all(buf["albedo"][sky] == 1)  # escape: chain throughput, emission is not demodulated
    centre = slice(SIZE // 2 - 1, SIZE // 2 + 1)  # the 2x2 pixels around the image centre
    assert np.all(coverage[centre, centre] == 1)
    np.testing.assert_allclose(buf["depth"][centre, centre, 0].mean(), 3.5, atol=0.02)
    np.testing.assert_allclose(buf["normal"][centre, centre].mean(axis=(0, 1)), [0, 0, 1], atol=0.02)


def test_same_seed_is_bit_identical_and_other_seeds_differ(variant):
    import mitsuba as mi

    scene = _mixed_scene(mi)
    first = render_buffers(scene, 4, seed=21)
    again = render_buffers(scene, 4, seed=21)
    other = render_buffers(scene, 4, seed=22)
    assert set(first) == {"diffuse", "specular", "albedo", "normal", "depth", "coverage", "diffuse_var", "specular_var"}
    for name in first:
        assert first[name].dtype == np.float32 and first[name].shape[:2] == (SIZE, SIZE)
        np.testing.assert_array_equal(first[name], again[name], err_msg=name)
    assert not np.allclose(first["diffuse"], other["diffuse"])
    assert not np.allclose(first["specular"], other["specular"])


def test_variance_buffer_matches_spread_of_independent_renders(variant):
    """Several passes per render (max_spp_per_pass < spp) also exercise the exact pass combination."""
    import mitsuba as mi

    scene = mi.load_dict(_cornell(mi))
    renders = [render_buffers(scene, 8, seed=100 + i, split=False, max_spp_per_pass=4) for i in range(8)]
    means = np.stack([r["diffuse"] for r in renders])
    empirical = means.var(axis=0, ddof=1).mean()
    predicted = np.stack([r["diffuse_var"] for r in renders]).mean()
    assert 0.75 < predicted / empirical < 1.33, (predicted, empirical)


def test_bad_arguments_raise(variant):
    import mitsuba as mi

    scene = mi.load_dict(_cornell(mi))
    with pytest.raises(ValueError, match="spp"):
        render_buffers(scene, 0, seed=0)
    with pytest.raises(ValueError, match="max_spp_per_pass"):
        render_buffers(scene, 4, seed=0, max_spp_per_pass=0)
    with pytest.raises(ValueError, match="seed"):
        render_buffers(scene, 4, seed=-1)
    gaussian = mi.cornell_box()
    gaussian["sensor"]["film"]["width"] = gaussian["sensor"]["film"]["height"] = 8
    with pytest.raises(ValueError, match="box reconstruction filter"):
        render_buffers(mi.load_dict(gaussian), 4, seed=0)
    register()
    with pytest.raises(Exception, match="rr_depth"):
        mi.load_dict({"type": INTEGRATOR_NAME, "rr_depth": 0})


def test_variants_are_only_those_the_integrator_accepts_and_llvm_is_found():
    from admc.pipeline.render.variants import PREFERENCE, VariantError, _llvm_major, find_llvm, resolve_variant

    assert resolve_variant("auto") in PREFERENCE
    for name in ("scalar_rgb", "llvm_ad_spectral"):
        with pytest.raises(VariantError, match=f"render.variant '{name}': the split integrator runs only in"):
            resolve_variant(name)
    assert [
        _llvm_major(p)
        for p in (
            "/usr/lib/x86_64-linux-gnu/libLLVM.so.19.1",
            "/usr/lib/x86_64-linux-gnu/libLLVM-15.so.1",
            "/usr/lib/llvm-19/lib/libLLVM.so.1",
            "/opt/libLLVM-18.so",
        )
    ] == [19, 15, 19, 18]
    library = find_llvm()  # setup installs libllvm19; the system's 15 crashes Mitsuba and must never be picked
    assert library is not None and _llvm_major(library) >= 16
