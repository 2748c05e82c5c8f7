"""The installed product: the shipped config layers travel with the package.

The slow test builds the wheel from exactly what deploy/Dockerfile copies into the image,
installs it into a fresh venv outside the checkout and runs that venv's `credit`; the fast
tests check the same wiring without building (package-data patterns, the Dockerfile's COPY
lines, the layer lookup and its errors).
"""

from __future__ import annotations

import fnmatch
import os
import re
import shutil
import subprocess
import sys
import sysconfig
import tomllib
from pathlib import Path

import pytest
import yaml

from cluster.config.schema import ConfigError
from cluster.config.shipped import config_root, default_files
from cluster.config.train import load_train_config
from learner.registry import ALGOS

ROOT = Path(__file__).resolve().parents[2]
CONFIGS = ROOT / "cluster" / "config" / "layers"
DOCKERFILE = ROOT / "deploy" / "Dockerfile"

# The seed's values (5.3.3 / 5.3.4) for EM-CAC on a SMAC-style map, as the shipped layers
# (envs/skirmish.yaml, algos/emcac.yaml) give them; the dataclass defaults differ in each.
EMCAC_SKIRMISH = {
    ("run", "num_envs"): 4,
    ("run", "test_interval"): 10_000,
    ("run", "t_max"): 2_000_000,
    ("cycling", "capacity"): 32,
    ("replay", "capacity"): 5000,
    ("replay", "batch_size"): 32,
    ("exploration", "epsilon_anneal_time"): 50_000,
    ("algo", "td_lambda"): 0.8,
    ("algo", "entropy_coef"): 0.1,
    ("algo", "kl_threshold"): 0.05,
    ("algo", "polyak_tau"): 0.05,
}


def assert_seed_values(cfg: dict) -> None:
    got = {key: cfg[key[0]][key[1]] for key in EMCAC_SKIRMISH}
    assert got == EMCAC_SKIRMISH
    assert cfg["algo_name"] == "emcac" and cfg["env"]["id"] == "skirmish/3s5z"


def docker_context() -> list[str]:
    """What the Dockerfile COPYs into the image before `RUN pip install .`."""
    sources: list[str] = []
    for line in DOCKERFILE.read_text().splitlines():
        if re.match(r"^RUN pip install \.$", line):
            return sources
        if line.startswith("COPY "):
            sources += line.split()[1:-1]
    raise AssertionError("deploy/Dockerfile has no `RUN pip install .`")


def shipped_layers() -> list[Path]:
    return sorted(p for p in CONFIGS.rglob("*.yaml"))


def test_every_shipped_layer_matches_a_package_data_pattern():
    meta = tomllib.loads((ROOT / "pyproject.toml").read_text())
    patterns = meta["tool"]["setuptools"]["package-data"]["cluster.config"]
    layers = shipped_layers()
    assert layers, f"no YAML under {CONFIGS}"
    for path in layers:
        rel = path.relative_to(ROOT / "cluster" / "config").as_posix()
        # setuptools globs each pattern from the package folder; `*` does not cross a `/`.
        assert any(fnmatch.fnmatch(rel, p) and rel.count("/") == p.count("/") for p in patterns), (
            f"{rel} is not package data of `cluster.config` (patterns {patterns})"
        )


def test_the_dockerfile_copies_every_package_before_installing_it():
    meta = tomllib.loads((ROOT / "pyproject.toml").read_text())
    packages = [p.rstrip("*") for p in meta["tool"]["setuptools"]["packages"]["find"]["include"]]
    copied = docker_context()
    assert set(packages) <= set(copied), f"image lacks {set(packages) - set(copied)}"
    assert "pyproject.toml" in copied
    text = DOCKERFILE.read_text()
    assert not re.search(r"^RUN pip install (-e|--editable)", text, re.M)


def test_layers_are_found_through_the_package():
    root = config_root()
    assert Path(str(root)) == CONFIGS  # this checkout's package
    names = [
        Path(str(p)).relative_to(CONFIGS).as_posix() for p in default_files("qmix", "skirmish/3m")
    ]
    assert names == [
        "envs/skirmish.yaml",
        "algos/qmix.yaml",
        "envs/skirmish.value.yaml",
        "envs/skirmish.qmix.yaml",
    ]


@pytest.mark.parametrize("algo", sorted(ALGOS))
def test_every_algorithm_and_env_family_has_its_required_layers(algo):
    for env in ("matrix/two_step", "skirmish/3m", "smac/3m"):
        assert default_files(algo, env)  # raises ConfigError naming a missing layer


def test_an_unknown_env_is_named_before_any_layer_is_looked_up():
    with pytest.raises(ConfigError, match="env: unknown env 'nowhere/3m'; valid envs:"):
        load_train_config("qmix", "nowhere/3m")


def run_credit(venv: Path, cwd: Path, *argv: str) -> subprocess.CompletedProcess:
    env = {k: v for k, v in os.environ.items() if k not in ("PYTHONPATH", "VIRTUAL_ENV")}
    env["CREDIT_STATE_DIR"] = str(cwd / "state")
    return subprocess.run(
        [str(venv / "bin" / "credit"), *argv],
        cwd=cwd,
        env=env,
        capture_output=True,
        text=True,
        timeout=300,
    )


@pytest.mark.slow
def test_a_wheel_installed_outside_the_checkout_trains_with_the_shipped_layers(tmp_path):
    # The Dockerfile's build context, copied the way its COPY lines copy it.
    ctx = tmp_path / "context"
    ctx.mkdir()
    ignore = shutil.ignore_patterns("__pycache__", "*.egg-info", "build")
    for src in docker_context():
        if (ROOT / src).is_dir():
            shutil.copytree(ROOT / src, ctx / src, ignore=ignore)
        else:
            shutil.copy2(ROOT / src, ctx / src)
    pip = [sys.executable, "-m", "pip"]
    build = subprocess.run(
        [*pip, "wheel", "--no-deps", "-q", str(ctx), "-w", str(tmp_path / "dist")],
        capture_output=True,
        text=True,
        timeout=600,
    )
    assert build.returncode == 0, build.stderr
    (wheel,) = (tmp_path / "dist").glob("credit-*.whl")

    # A fresh venv holding only the wheel; the dependencies (torch, ray, ...) are read from
    # this interpreter's site-packages through a .pth line, which adds that folder as a plain
    # path: its editable-install hook (pointing at the checkout) is not run.
    venv = tmp_path / "venv"
    subprocess.run([sys.executable, "-m", "venv", "--without-pip", str(venv)], check=True)
    install = subprocess.run(
        [*pip, "--python", str(venv / "bin" / "python"), "install", "-q", "--no-deps", str(wheel)],
        capture_output=True,
        text=True,
        timeout=300,
    )
    assert install.returncode == 0, install.stderr
    site = Path(
        subprocess.run(
            [
                str(venv / "bin" / "python"),
                "-c",
                "import sysconfig; print(sysconfig.get_paths()['purelib'])",
            ],
            capture_output=True,
            text=True,
            check=True,
        ).stdout.strip()
    )
    (site / "deps.pth").write_text(sysconfig.get_paths()["purelib"] + "\n")
    elsewhere = tmp_path / "elsewhere"
    elsewhere.mkdir()
    outside = {k: v for k, v in os.environ.items() if k not in ("PYTHONPATH", "VIRTUAL_ENV")}
    where = subprocess.run(
        [str(venv / "bin" / "python"), "-c", "import cluster.cli; print(cluster.cli.__file__)"],
        cwd=elsewhere,
        env=outside,  # as run_credit: a PYTHONPATH at a checkout would import that instead
        capture_output=True,
        text=True,
        check=True,
    ).stdout.strip()
    assert Path(where).is_relative_to(site), f"imported {where}, not the installed copy"

    printed = run_credit(
        venv, elsewhere, "train", "--algo", "emcac", "--env", "skirmish/3s5z", "--print-config"
    )
    assert printed.returncode == 0, printed.stderr
    assert_seed_values(yaml.safe_load(printed.stdout))
    layers = [line.split()[-1] for line in printed.stdout.splitlines() if line.startswith("#   /")]
    assert [
        Path(p).relative_to(site / "cluster" / "config" / "layers").as_posix() for p in layers
    ] == [
        "envs/skirmish.yaml",
        "algos/emcac.yaml",
    ]

    # A real (one-round) training writes the same values to config.yaml.
    trained = run_credit(
        venv, elsewhere, "train", "--algo", "emcac", "--env", "skirmish/3s5z",
        "--t-max", "1", "--out", "run",
    )  # fmt: skip
    assert trained.returncode == 0, trained.stderr
    written = yaml.safe_load((elsewhere / "run" / "config.yaml").read_text())
    assert_seed_values({**written, "run": {**written["run"], "t_max": 2_000_000}})
    assert written["run"]["t_max"] == 1

    # An install that lost a layer stops with exit code 2, naming the missing file.
    (site / "cluster" / "config" / "layers" / "algos" / "emcac.yaml").unlink()
    broken = run_credit(
        venv, elsewhere, "train", "--algo", "emcac", "--env", "skirmish/3s5z", "--print-config"
    )
    assert broken.returncode == 2
    assert (
        "shipped config layer" in broken.stderr and "algos/emcac.yaml is missing" in broken.stderr
    )
