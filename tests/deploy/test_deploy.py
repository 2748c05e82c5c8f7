"""deploy/: Ray launcher YAML through Ray's own validation; KubeRay manifests; Dockerfile."""

from __future__ import annotations

import copy
import re
import shutil
import subprocess
from pathlib import Path

import pytest
import yaml

ROOT = Path(__file__).resolve().parents[2]
DEPLOY = ROOT / "deploy"
RAY_YAMLS = sorted((DEPLOY / "ray").glob("*.yaml"))


def load(path: Path) -> dict:
    data = yaml.safe_load(path.read_text())
    assert isinstance(data, dict), f"{path} is not a mapping"
    return data


def ray_validate(config: dict) -> dict:
    """What `ray up` does before touching a cloud: fill defaults, then validate."""
    pytest.importorskip("jsonschema", reason="Ray's config validation needs jsonschema")
    from ray.autoscaler._private.util import prepare_config, validate_config

    prepared = prepare_config(copy.deepcopy(config))
    validate_config(prepared)
    return prepared


def test_there_are_ray_launcher_configs():
    assert {p.name for p in RAY_YAMLS} >= {"cluster.yaml"}


@pytest.mark.parametrize("path", RAY_YAMLS, ids=lambda p: p.name)
def test_ray_yaml_passes_rays_validation(path):
    prepared = ray_validate(load(path))
    assert prepared["head_node_type"] in prepared["available_node_types"]
    head_cmds = " ".join(prepared["head_start_ray_commands"])
    assert "ray start --head" in head_cmds
    assert "$RAY_HEAD_IP" in " ".join(prepared["worker_start_ray_commands"])


@pytest.mark.parametrize(
    "breakage",
    [
        lambda c: c.__setitem__("no_such_field", 1),
        lambda c: c["provider"].pop("type"),
        lambda c: c.__setitem__("max_workers", "many"),
    ],
)
def test_rays_validation_does_reject_a_broken_config(breakage):
    config = load(DEPLOY / "ray" / "cluster.yaml")
    breakage(config)
    with pytest.raises(Exception):  # noqa: B017 - jsonschema or Ray's own error types
        ray_validate(config)


def check_pod_template(template: dict, where: str) -> None:
    containers = template["spec"]["containers"]
    assert containers, f"{where}: no containers"
    for c in containers:
        assert c.get("name") and c.get("image"), f"{where}: container needs name and image"
        assert "credit" in c["image"], f"{where}: not the credit image"


def check_ray_cluster_spec(spec: dict, where: str) -> None:
    head = spec["headGroupSpec"]
    assert isinstance(head["rayStartParams"], dict), f"{where}: head rayStartParams"
    check_pod_template(head["template"], f"{where}.headGroupSpec")
    groups = spec["workerGroupSpecs"]
    assert groups, f"{where}: no worker groups"
    for g in groups:
        name = g["groupName"]
        assert isinstance(g["rayStartParams"], dict), f"{where}.{name}: rayStartParams"
        for key in ("replicas", "minReplicas", "maxReplicas"):
            assert isinstance(g[key], int), f"{where}.{name}: {key} must be an integer"
        assert g["minReplicas"] <= g["replicas"] <= g["maxReplicas"], f"{where}.{name}"
        check_pod_template(g["template"], f"{where}.{name}")


def test_kuberay_raycluster():
    doc = load(DEPLOY / "kuberay" / "raycluster.yaml")
    assert doc["apiVersion"] == "ray.io/v1" and doc["kind"] == "RayCluster"
    assert doc["metadata"]["name"]
    check_ray_cluster_spec(doc["spec"], "RayCluster.spec")


def test_kuberay_rayjob_runs_a_cluster_training():
    doc = load(DEPLOY / "kuberay" / "rayjob.yaml")
    assert doc["apiVersion"] == "ray.io/v1" and doc["kind"] == "RayJob"
    assert doc["metadata"]["name"]
    entry = " ".join(doc["spec"]["entrypoint"].split())
    assert entry.startswith("credit train --mode cluster --address auto"), entry
    check_ray_cluster_spec(doc["spec"]["rayClusterSpec"], "RayJob.spec.rayClusterSpec")


def test_ray_versions_match_the_installed_ray():
    import ray

    for name in ("raycluster.yaml", "rayjob.yaml"):
        doc = load(DEPLOY / "kuberay" / name)
        spec = doc["spec"].get("rayClusterSpec", doc["spec"])
        assert spec["rayVersion"] == ray.__version__, name


def test_dockerfile_installs_the_pinned_cpu_torch_and_the_project():
    text = (DEPLOY / "Dockerfile").read_text()
    pin = re.search(r'"torch==([^"]+)"', (ROOT / "pyproject.toml").read_text())
    assert pin, "pyproject.toml no longer pins torch"
    assert f"torch=={pin.group(1)} --index-url https://download.pytorch.org/whl/cpu" in text
    assert re.search(r"^RUN pip install \.$", text, re.M)
    assert re.search(r"^FROM python:3\.11", text, re.M)


def test_prometheus_config_uses_file_sd():
    doc = load(DEPLOY / "prometheus" / "prometheus.yml")
    jobs = {j["job_name"]: j for j in doc["scrape_configs"]}
    assert jobs["credit"]["file_sd_configs"][0]["files"]


@pytest.mark.skipif(shutil.which("promtool") is None, reason="promtool not on PATH")
def test_prometheus_config_passes_promtool():
    out = subprocess.run(
        ["promtool", "check", "config", str(DEPLOY / "prometheus" / "prometheus.yml")],
        capture_output=True,
        text=True,
        timeout=60,
    )
    assert out.returncode == 0, out.stdout + out.stderr
