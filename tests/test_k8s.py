"""The Kubernetes manifests (docker/k8s/) against the schemas of a named Kubernetes version
(kubernetes-validate, strict: an unknown or misspelt field fails), and what they promise: probes
on /readyz and /healthz, one torch thread and one CPU per pod, keys from a secret."""

from __future__ import annotations

import copy
from pathlib import Path

import pytest

from tests.needs import import_or_missing

kubernetes_validate = import_or_missing(
    "kubernetes_validate", "kubernetes-validate not installed (the dev extra has it)"
)
yaml = import_or_missing("yaml", "PyYAML not installed (kubernetes-validate needs it)")

K8S_DIR = Path(__file__).resolve().parents[1] / "docker" / "k8s"
KUBERNETES = "1.32.0"


def documents(name: str) -> list[dict]:
    return [doc for doc in yaml.safe_load_all((K8S_DIR / name).read_text()) if doc]


def by_kind(docs: list[dict]) -> dict[str, dict]:
    return {doc["kind"]: doc for doc in docs}


def test_the_plain_service_manifests_validate_strictly():
    docs = documents("ds3d.yaml")
    assert set(by_kind(docs)) == {"Deployment", "Service", "HorizontalPodAutoscaler"}
    for doc in docs:
        kubernetes_validate.validate(doc, KUBERNETES, strict=True)


def test_a_misspelt_field_fails_validation():
    deployment = copy.deepcopy(by_kind(documents("ds3d.yaml"))["Deployment"])
    container = deployment["spec"]["template"]["spec"]["containers"][0]
    container["readinesProbe"] = container.pop("readinessProbe")
    with pytest.raises(kubernetes_validate.ValidationError):
        kubernetes_validate.validate(deployment, KUBERNETES, strict=True)


def test_the_deployment_probes_and_sizes_each_pod_as_the_service_expects():
    kinds = by_kind(documents("ds3d.yaml"))
    pod = kinds["Deployment"]["spec"]["template"]["spec"]
    (container,) = pod["containers"]
    assert container["readinessProbe"]["httpGet"]["path"] == "/readyz"
    assert container["livenessProbe"]["httpGet"]["path"] == "/healthz"
    env = {e["name"]: e for e in container["env"]}
    # the CPU limit sizes the pod's processes and threads (ds3d_service.settings): one CPU, one
    # process of one thread, which no env var overrides
    assert container["resources"]["limits"]["cpu"] == "1"
    assert not {"DS3D_WORKERS", "DS3D_TORCH_THREADS"} & set(env)
    assert "secretKeyRef" in env["DS3D_API_KEYS"]["valueFrom"]  # closed: keys from a secret
    assert container["resources"]["requests"]["cpu"] == container["resources"]["limits"]["cpu"]
    port = container["ports"][0]["name"]
    assert kinds["Service"]["spec"]["ports"][0]["targetPort"] == port
    target = kinds["HorizontalPodAutoscaler"]["spec"]["scaleTargetRef"]
    assert (target["kind"], target["name"]) == (
        "Deployment",
        kinds["Deployment"]["metadata"]["name"],
    )


def test_the_rayservice_runs_the_serve_application_on_valid_pods():
    (service,) = documents("rayservice.yaml")
    assert (service["apiVersion"], service["kind"]) == ("ray.io/v1", "RayService")
    cluster = service["spec"]["rayClusterConfig"]
    groups = [cluster["headGroupSpec"], *cluster["workerGroupSpecs"]]
    for group in groups:  # KubeRay's pod templates are Kubernetes PodTemplateSpecs
        pod = {"apiVersion": "v1", "kind": "Pod", "metadata": {"name": "ray"}}
        kubernetes_validate.validate(pod | group["template"], KUBERNETES, strict=True)
    (workers,) = cluster["workerGroupSpecs"]
    assert workers["rayStartParams"]["num-cpus"] == "1"  # one replica (one CPU) per worker
    # the Serve config names the module's application builder and only its scaling keys
    config = yaml.safe_load(service["spec"]["serveConfigV2"])
    (application,) = config["applications"]
    module, builder = application["import_path"].split(":")
    assert (module, builder) == ("ds3d_service.ray_serve", "app_builder")
    source = (K8S_DIR.parents[1] / "ds3d_service" / "ray_serve.py").read_text()
    assert f"def {builder}(" in source
    local = yaml.safe_load((K8S_DIR.parent / "ray-serve.yaml").read_text())["applications"][0]
    assert set(application["args"]) == set(local["args"])
