"""Small configurations of every registered method, for tests that must run each method end to
end in seconds on a test-size scene (``tests/methods/test_threads.py``,
``tests/reports/test_executors.py``). Every stage the default config runs is still run — only
resolutions, sample and term counts are small. Not used by real runs.

``CASES``: case name → (method, test-size scene, config). PTT appears twice: the smoke suite's
PCA basis with CTA compression is code of its own.
"""
from __future__ import annotations

_PTT = {"rays": 32, "cube_res": 8, "n_L": 48, "brdf_grid": 12, "brdf_table": 16, "lobe_fit_samples": 4096,
        "lobe_vis_samples": 1024}

CASES: dict[str, tuple[str, str, dict]] = {
    "inout": ("inout", "sphere_plane", {"brdf_res": 12, "cube_res": 8, "n_coeffs": 48, "lut_res": 16}),
    "inout-vertex": ("inout", "sphere_plane", {"brdf_res": 12, "cube_res": 8, "n_coeffs": 48, "lut_res": 16,
                                               "shading": "vertex"}),
    "oracle": ("oracle", "sphere_plane", {"brdf_samples": 4, "light_samples": 4}),
    "ptt": ("ptt", "sphere_plane", {**_PTT, "light_res_1": 4}),
    "ptt-pca-compressed": ("ptt", "sphere_plane", {**_PTT, "basis": "pca", "pca_grid": 8, "lobe_theta": 8,
                                                   "light_res_1": 2, "sh_order": 2,
                                                   "compress": {"clusters": 2, "eigenvectors": 8, "light_dim": 16}}),
    "sh_prt": ("sh_prt", "creature", {"rays": 64}),
    "triple_product": ("triple_product", "sphere_plane", {"level": 2}),
    "zh_shadow": ("zh_shadow", "creature", {"train_poses": 6, "n_dirs": 256, "fit_iters": 10}),
    # order 3: 9-row float32 products, a shape MKL splits over threads (methods.core.threads)
    "zh_shadow-order3": ("zh_shadow", "creature", {"train_poses": 6, "n_dirs": 256, "fit_iters": 10, "order": 3}),
    # the cosine variant shaded per vertex (the suites' ZH_PHYSICAL_VERTEX at order 3): frame rotations
    # (runtime.zonal_conjugate) and 9-row products again
    "zh_shadow-order3-vertex-cosine": ("zh_shadow", "creature", {"train_poses": 6, "n_dirs": 256, "fit_iters": 10,
                                                                 "order": 3, "shading": "vertex",
                                                                 "specular": "cosine"}),
}


def project_methods() -> set[str]:
    """The registered methods that ship with the project (``methods.*``), without the test doubles
    other tests in the same process may have registered (``testing.fakes``)."""
    from methods.registry import available_methods, get_method

    return {n for n in available_methods() if get_method(n).__module__.startswith("methods.")}
