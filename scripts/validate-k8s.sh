#!/usr/bin/env bash
# Offline validation of the Kubernetes manifests (deploy/kubernetes): each kustomization is built
# with `kubectl kustomize` and every object is checked against the Kubernetes OpenAPI schemas
# bundled in kubernetes-validate (PyPI), strictly (unknown fields are errors). No cluster needed.
#
# Custom resources have no bundled schema: kubernetes-validate only warns about them. Those
# warnings are not ignored: every one must be for a kind listed in CRD_KINDS below, and each such
# object gets a structural check here instead (what this repository relies on: the scale target
# exists in the same build, the trigger reads kairos_queue_depth; a PodMonitor selects pods of
# the build on their `metrics` port; the PrometheusRule carries exactly the rules of
# deploy/monitoring/kairos.rules.yml). Any other warning fails.
#
# Installs kubernetes-validate into .venv-k8s/ on first use (about 40 s; then offline).
set -euo pipefail
cd "$(dirname "$0")/.."

K8S_VALIDATE_DEPS=(kubernetes-validate==1.37.0)
if ! .venv-k8s/bin/kubernetes-validate --version >/dev/null 2>&1; then
    python3 -m venv .venv-k8s
    .venv-k8s/bin/pip install --quiet --disable-pip-version-check "${K8S_VALIDATE_DEPS[@]}"
fi
if ! command -v kubectl >/dev/null; then
    echo "validate-k8s: kubectl not found (it ships with this machine image; install kubectl)" >&2
    exit 1
fi

# The Kubernetes version the manifests target (kubernetes-validate's newest bundled schemas).
K8S_VERSION=1.37.0
# Custom resource kinds with no bundled schema, checked structurally below instead.
CRD_KINDS="ScaledObject PodMonitor PrometheusRule"

out=$(mktemp -d)
trap 'rm -rf "$out"' EXIT
builds=(base overlays/edge-site overlays/cloud-site)
for build in "${builds[@]}"; do
    file="$out/$(echo "$build" | tr / -).yaml"
    kubectl kustomize "deploy/kubernetes/$build" >"$file"
    report=$(.venv-k8s/bin/kubernetes-validate --strict -k "$K8S_VERSION" "$file" 2>&1) || {
        echo "$report" >&2
        echo "validate-k8s: $build: invalid" >&2
        exit 1
    }
    unexpected=$(echo "$report" | grep -E '^(WARN|ERROR)' | grep -vE "Couldn't find schema for kind ($(echo "$CRD_KINDS" | tr ' ' '|')) " || true)
    if [ -n "$unexpected" ]; then
        echo "$unexpected" >&2
        echo "validate-k8s: $build: unexpected warnings" >&2
        exit 1
    fi
    passed=$(echo "$report" | grep -c '^INFO .* passed' || true)
    skipped=$(echo "$report" | grep -c "Couldn't find schema" || true)
    echo "validate-k8s: $build: $passed objects valid (strict, Kubernetes $K8S_VERSION), $skipped custom resources checked structurally"
    .venv-k8s/bin/python - "$file" "$CRD_KINDS" deploy/monitoring/kairos.rules.yml <<'PY'
import sys
import yaml

path, crd_kinds, rules_path = sys.argv[1], sys.argv[2].split(), sys.argv[3]
docs = [d for d in yaml.safe_load_all(open(path)) if d]
deployments = {d["metadata"]["name"] for d in docs if d["kind"] == "Deployment"}
kinds = {d["kind"] for d in docs}
errors = []
for d in docs:
    if d["kind"] == "ScaledObject":
        name = d["metadata"]["name"]
        spec = d.get("spec", {})
        known = {"scaleTargetRef", "minReplicaCount", "maxReplicaCount", "pollingInterval",
                 "cooldownPeriod", "triggers", "advanced", "fallback", "idleReplicaCount"}
        if set(spec) - known:
            errors.append(f"ScaledObject {name}: unknown spec fields {sorted(set(spec) - known)}")
        target = spec.get("scaleTargetRef", {})
        if target.get("kind", "Deployment") != "Deployment" or target.get("name") not in deployments:
            errors.append(f"ScaledObject {name}: scaleTargetRef {target} is not a Deployment of this build")
        if not 0 <= spec.get("minReplicaCount", 0) <= spec.get("maxReplicaCount", 100):
            errors.append(f"ScaledObject {name}: minReplicaCount > maxReplicaCount")
        triggers = spec.get("triggers", [])
        if not triggers:
            errors.append(f"ScaledObject {name}: no trigger")
        for t in triggers:
            meta = t.get("metadata", {})
            if t.get("type") != "prometheus":
                errors.append(f"ScaledObject {name}: trigger type {t.get('type')!r}, expected prometheus")
            for key in ("serverAddress", "query", "threshold"):
                if not isinstance(meta.get(key), str) or not meta.get(key):
                    errors.append(f"ScaledObject {name}: trigger metadata.{key} must be a non-empty string")
            if "kairos_queue_depth" not in meta.get("query", ""):
                errors.append(f"ScaledObject {name}: the query does not read kairos_queue_depth")
            try:
                float(meta.get("threshold", ""))
            except ValueError:
                errors.append(f"ScaledObject {name}: threshold is not a number")
    elif d["kind"] == "PodMonitor":
        name = d["metadata"]["name"]
        spec = d.get("spec", {})
        wanted = spec.get("selector", {}).get("matchLabels", {})
        pods = [p for p in docs if p["kind"] == "Deployment"
                and wanted and wanted.items() <= p["spec"]["template"]["metadata"].get("labels", {}).items()]
        if not pods:
            errors.append(f"PodMonitor {name}: selects no Deployment's pods in this build")
        endpoints = spec.get("podMetricsEndpoints", [])
        if not endpoints:
            errors.append(f"PodMonitor {name}: no podMetricsEndpoints")
        for e in endpoints:
            for p in pods:
                ports = {port.get("name") for c in p["spec"]["template"]["spec"]["containers"]
                         for port in c.get("ports", [])}
                if e.get("port") not in ports:
                    errors.append(f"PodMonitor {name}: port {e.get('port')!r} is not a port of {p['metadata']['name']}")
            if e.get("path", "/metrics") != "/metrics":
                errors.append(f"PodMonitor {name}: path {e.get('path')!r}, expected /metrics")
    elif d["kind"] == "PrometheusRule":
        shipped = yaml.safe_load(open(rules_path))
        if d.get("spec") != shipped:
            errors.append(f"PrometheusRule {d['metadata']['name']}: its spec differs from {rules_path}")
    elif d["kind"] == "HorizontalPodAutoscaler":
        target = d["spec"]["scaleTargetRef"]
        if target["name"] not in deployments:
            errors.append(f"HPA {d['metadata']['name']}: target {target['name']} is not a Deployment of this build")
for d in docs:
    group = d["apiVersion"].split("/")[0] if "/" in d["apiVersion"] else ""
    custom = "." in group and not group.endswith(".k8s.io")
    if custom and d["kind"] not in crd_kinds:
        errors.append(f"{d['kind']} ({d['apiVersion']}): a custom resource not listed in CRD_KINDS")
if {"ScaledObject", "HorizontalPodAutoscaler"} <= kinds:
    errors.append("both a KEDA ScaledObject and an HPA: they would fight over the replicas")
if errors:
    print("\n".join(errors), file=sys.stderr)
    sys.exit(1)
PY
done
