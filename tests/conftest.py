"""Shared fixtures: a small rendered BOP dataset of the committed catalog, template banks."""

import atexit
import os
import shutil
import tempfile

import numpy as np
import pytest

from posefuse.estimator.core.camera import Camera
from posefuse.estimator.core.objects import load_catalog
from posefuse.service.resources import DEFAULT_CATALOG
from posefuse.sim.scenes import SceneSpec
from posefuse.sim.synth import SynthConfig, generate_dataset

# one template cache for the whole test session, never the user's
os.environ["POSEFUSE_CACHE"] = tempfile.mkdtemp(prefix="posefuse-test-cache-")
atexit.register(shutil.rmtree, os.environ["POSEFUSE_CACHE"], ignore_errors=True)

# the longest tests that need no shared fixture start first: the two workers then end
# together, instead of one running them alone after the other is done (the suite ran 15:03 with
# them in their places on the 2-core machine)
LONGEST_FIRST = (
    "tests/sim/test_onboard.py::test_onboard_then_serve_the_part_set",
    "tests/estimator/core/test_objects_catalog.py::test_committed_catalog_is_what_the_generator_writes",
)


def pytest_collection_modifyitems(config, items):
    first = [item for item in items if item.nodeid in LONGEST_FIRST]
    items[:] = first + [item for item in items if item.nodeid not in LONGEST_FIRST]


SMALL_CAMERA = Camera(np.array([[462.0, 0, 320.0], [0, 462.0, 180.0], [0, 0, 1]]), 640, 360)


@pytest.fixture(scope="session")
def robi_catalog():
    return load_catalog(DEFAULT_CATALOG)


def render_small_dataset(root, catalog, n_scenes: int, seed: int, instances, n_views: int):
    """Bins of the catalog at 640x360 as a BOP dataset under root."""
    config = SynthConfig(
        n_scenes=n_scenes,
        seed=seed,
        camera=SMALL_CAMERA,
        scene=SceneSpec(n_instances=instances, n_views=n_views),
    )
    return generate_dataset(catalog, root, config, show_progress=False)


@pytest.fixture(scope="session")
def small_dataset_root(tmp_path_factory, robi_catalog):
    """2 scenes x 3 views at 640x360 (a few seconds to render)."""
    root = tmp_path_factory.mktemp("bop") / "small"
    return render_small_dataset(root, robi_catalog, 2, 11, (6, 8), 3)


@pytest.fixture(scope="session")
def default_banks(robi_catalog, tmp_path_factory):
    """Template banks of the committed catalog at the default parameters (~6 s to build)."""
    from posefuse.estimator.rotation.templates import build_template_banks

    # the session's POSEFUSE_CACHE, so commands run by the tests find them too
    return build_template_banks([robi_catalog[k] for k in robi_catalog])


FULL_RES_VIEWS = 4


@pytest.fixture(scope="session")
def full_res_dataset(tmp_path_factory, robi_catalog):
    """One full-resolution bin scene of 6-8 parts seen from FULL_RES_VIEWS views."""
    from posefuse.sim.scenes import SceneSpec
    from posefuse.sim.synth import SynthConfig, generate_dataset

    root = tmp_path_factory.mktemp("full") / "bin"
    config = SynthConfig(
        n_scenes=1, seed=77, scene=SceneSpec(n_instances=(6, 8), n_views=FULL_RES_VIEWS)
    )
    return generate_dataset(robi_catalog, root, config, show_progress=False)


def extra_shared(*parts: str):
    """A path under the folder ``POSEFUSE_SHARED`` names (the project's ../shared: real meshes,
    reference figures). A test that needs it is an *extra* (its name says so): skipped where the
    variable is unset, failed where it is set and the path is missing; it never falls back to
    something else."""
    from pathlib import Path

    root = os.environ.get("POSEFUSE_SHARED")
    if not root:
        pytest.skip("extra: set POSEFUSE_SHARED to the shared folder (.ci/run does)")
    path = Path(root, *parts)
    if not path.exists():
        pytest.fail(f"POSEFUSE_SHARED={root}: {path} is missing")
    return path
