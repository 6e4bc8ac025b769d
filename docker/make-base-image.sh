#!/usr/bin/env bash
# Builds a local stand-in for the public `python:3.11-slim-bookworm` image, for machines that
# reach Debian's package mirror but no image registry:
#   1. `debootstrap --variant=minbase` a Debian bookworm root filesystem and `docker import` it;
#   2. build docker/base.Dockerfile on top of it (Debian's python3, which is 3.11 on bookworm).
# Idempotent: does nothing when the final tag exists, and reuses the imported root filesystem.
# Usage: docker/make-base-image.sh [TAG]   (default: crestereo-local/python:3.11-slim-bookworm)
# Env:   DEBIAN_MIRROR (default http://deb.debian.org/debian), ROOTFS_TAG.
set -euo pipefail
here=$(cd "$(dirname "$0")" && pwd)
tag=${1:-${BASE_IMAGE:-crestereo-local/python:3.11-slim-bookworm}}
rootfs_tag=${ROOTFS_TAG:-crestereo-local/debian:bookworm-minbase}
mirror=${DEBIAN_MIRROR:-http://deb.debian.org/debian}

if docker image inspect "$tag" >/dev/null 2>&1; then
    echo "base image $tag exists"
    exit 0
fi

if ! docker image inspect "$rootfs_tag" >/dev/null 2>&1; then
    command -v debootstrap >/dev/null || { echo "debootstrap is not installed (apt-get install debootstrap)" >&2; exit 1; }
    work=$(mktemp -d /var/tmp/crestereo-rootfs.XXXXXX)
    trap 'rm -rf "$work"' EXIT
    echo "debootstrap bookworm (minbase) from $mirror ..."
    debootstrap --variant=minbase --components=main bookworm "$work/rootfs" "$mirror" >"$work/debootstrap.log" 2>&1 \
        || { tail -n 30 "$work/debootstrap.log" >&2; exit 1; }
    # Security and point-release updates, as the public Debian images have them.
    cat >"$work/rootfs/etc/apt/sources.list" <<SOURCES
deb $mirror bookworm main
deb $mirror bookworm-updates main
deb http://deb.debian.org/debian-security bookworm-security main
SOURCES
    # As in the official debian:bookworm-slim image: no docs (but the copyright files), man pages,
    # translations, package caches or lists, now and in what later layers install.
    cat >"$work/rootfs/etc/dpkg/dpkg.cfg.d/docker-slim" <<'DPKG'
path-exclude /usr/share/doc/*
path-include /usr/share/doc/*/copyright
path-exclude /usr/share/man/*
path-exclude /usr/share/info/*
path-exclude /usr/share/groff/*
path-exclude /usr/share/lintian/*
path-exclude /usr/share/locale/*
DPKG
    cat >"$work/rootfs/etc/apt/apt.conf.d/docker-clean" <<'APT'
DPkg::Post-Invoke { "rm -f /var/cache/apt/archives/*.deb /var/cache/apt/archives/partial/*.deb /var/cache/apt/*.bin || true"; };
APT::Update::Post-Invoke { "rm -f /var/cache/apt/archives/*.deb /var/cache/apt/archives/partial/*.deb /var/cache/apt/*.bin || true"; };
Dir::Cache::pkgcache "";
Dir::Cache::srcpkgcache "";
Acquire::Languages "none";
APT::Install-Recommends "false";
APT
    find "$work/rootfs/usr/share/doc" -mindepth 1 ! -name copyright ! -type d -delete
    rm -rf "$work/rootfs"/usr/share/man/* "$work/rootfs"/usr/share/info/* "$work/rootfs"/usr/share/locale/* \
        "$work/rootfs"/var/cache/apt/*.bin "$work/rootfs"/var/cache/apt/archives/*.deb \
        "$work/rootfs"/var/lib/apt/lists/* "$work/rootfs"/var/log/*.log "$work/rootfs"/var/cache/debconf/*-old
    tar --numeric-owner -C "$work/rootfs" -c . \
        | docker import --change 'CMD ["bash"]' --message "debootstrap --variant=minbase bookworm" - "$rootfs_tag" >/dev/null
    echo "imported $rootfs_tag"
fi

# --network host: the build's apt-get reaches the mirror exactly as this host does.
# No build context: the Dockerfile comes on standard input. Its log goes to a file (tail on failure).
log=$(mktemp /var/tmp/crestereo-base-build.XXXXXX.log)
docker build --network host --build-arg "ROOTFS=$rootfs_tag" -t "$tag" - <"$here/base.Dockerfile" >"$log" 2>&1 \
    || { tail -n 40 "$log" >&2; exit 1; }
rm -f "$log"
docker image inspect --format "base image {{index .RepoTags 0}}: {{.Size}} bytes" "$tag"
