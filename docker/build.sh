#!/usr/bin/env bash
# Builds the service image on this kind of machine: no image registry, no PyTorch index.
#  - base image: made locally by make-base-image.sh (debootstrap + docker import), once;
#  - torch: the host's CPU wheel (from its pip find-links dirs), staged in docker/build-extras/wheels;
#  - pip inside the build: the host's package index and CA bundle.
# Usage: docker/build.sh [extra `docker build` arguments]    Env: IMAGE, BASE_IMAGE, TORCH_VERSION
set -euo pipefail
root=$(cd "$(dirname "$0")/.." && pwd)
image=${IMAGE:-crestereo-pp:latest}
base=${BASE_IMAGE:-crestereo-local/python:3.11-slim-bookworm}
torch_version=${TORCH_VERSION:-2.13.0+cpu}
extras=$root/docker/build-extras

# One build at a time on this engine (several checkouts may run the test suite at once): the
# cache pruning below must not race another build's intermediate images.
if { exec 9>>/var/tmp/crestereo-docker-build.lock; } 2>/dev/null; then
    flock 9
fi

"$root/docker/make-base-image.sh" "$base"

pip_config() { python3 -m pip config get "global.$1" 2>/dev/null || true; }

# The host's CPU wheel of torch, if it has one (hard link when possible: no copy of 190 MB).
mkdir -p "$extras/wheels"
torch_index=https://download.pytorch.org/whl/cpu
for dir in ${PIP_FIND_LINKS:-} $(pip_config find-links) /opt/wheels; do
    for wheel in "$dir"/torch-"$torch_version"-cp311-cp311-*"$(uname -m)".whl; do
        [ -f "$wheel" ] || continue
        target=$extras/wheels/$(basename "$wheel")
        if [ ! -f "$target" ] || [ "$(stat -c %s "$wheel")" != "$(stat -c %s "$target")" ]; then
            ln -f "$wheel" "$target" 2>/dev/null || cp "$wheel" "$target"
        fi
        torch_index=""   # found: torch's own dependencies then come from the ordinary index
    done
done

# The host's CA bundle, for an index behind a TLS-intercepting proxy.
cert=${PIP_CERT:-$(pip_config cert)}
cert=${cert:-/etc/ssl/certs/ca-certificates.crt}
if [ -f "$cert" ] && ! cmp -s "$cert" "$extras/ca-bundle.crt"; then
    cp "$cert" "$extras/ca-bundle.crt"
fi

index=${PIP_INDEX_URL:-$(pip_config index-url)}
index=${index:-https://pypi.org/simple}

# --network host: pip in the build reaches the index exactly as this host does.
args=(--network host
      --build-arg "BASE_IMAGE=$base"
      --build-arg "TORCH_VERSION=$torch_version"
      --build-arg "TORCH_INDEX_URL=${torch_index:-$index}"
      --build-arg "PIP_INDEX_URL=$index"
      -f docker/Dockerfile)

# The build context as .dockerignore selects it (its `!path` lines, less its `**/name` lines), sent
# as a tar in which every file has the same time: the legacy builder keys a COPY's layer cache on
# its files' times as well as their contents, so a fresh clone of unchanged code (new times)
# would build the graphs stage again (a minute and a half of export) for nothing.
include=() exclude=()
while read -r line; do
    case $line in
        '!'*) include+=("${line#!}") ;;
        '**/'*) exclude+=("--exclude=${line#\*\*/}") ;;
    esac
done < "$root/.dockerignore"
context() {
    tar --create --file=- --directory="$root" --sort=name --mtime=@0 --owner=0 --group=0 --numeric-owner \
        "${exclude[@]}" docker/Dockerfile "${include[@]}"
}
context | docker build "${args[@]}" -t "$image" "$@" -

# The legacy builder keeps its layer cache in untagged images, and a rebuild leaves the previous
# ones behind. Tag the slow stages (all cached here: the dependencies, torch and the rest; lite's
# graph, minutes of export) so that they stay, then drop what is untagged and unused.
for stage in deps graphs; do
    context | docker build "${args[@]}" --quiet --target "$stage" -t "${image%:*}:$stage-cache" - >/dev/null
done
docker image prune --force >/dev/null
docker image inspect --format "image $image: {{.Size}} bytes" "$image"
