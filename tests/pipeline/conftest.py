"""The reduced demo case (datasets_tools QUICK size), made once per test session."""

import dataclasses

import pytest

from clflow.scene.config import load_config


@pytest.fixture(scope="session")
def quick_demo(tmp_path_factory):
    """Folder of the QUICK demo: scene.ply, guidance/ frames, config.yaml, config_truth.yaml."""
    from clflow_datasets.demo import QUICK, make_demo

    folder = tmp_path_factory.mktemp("demo")
    make_demo(folder, QUICK)
    return folder


@pytest.fixture
def demo_config(quick_demo, tmp_path):
    """The demo's config with its output in this test's own folder; ``iterations`` overrides."""

    def load(iterations=None, name="results"):
        cfg = load_config(quick_demo / "config.yaml")
        cfg = dataclasses.replace(cfg, output=tmp_path / name)
        if iterations is not None:
            cfg = dataclasses.replace(cfg, optimize=dataclasses.replace(cfg.optimize, iterations=iterations))
        return cfg

    return load


@pytest.fixture
def points_one_by_one(monkeypatch):
    """Every batch evaluated point by point through ``Objective.evaluate``, as the CPU plan
    does, so that a test's stand-in for ``evaluate`` sees every run even where the kernel
    plan would simulate a batch as one population (the GPU plan: CLFLOW_KERNELS=gpu)."""
    from clflow.pipeline.fit import objective

    monkeypatch.setattr(objective, "populations_pay", lambda: False)
