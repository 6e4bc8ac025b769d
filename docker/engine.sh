#!/usr/bin/env bash
# Makes sure a Docker engine answers `docker info`: starts the installed dockerd (as root) when none
# runs. With --install, first installs Debian's engine, debootstrap and docker-compose when missing.
# Idempotent and quick where the engine already runs. Exit 1, with the reason on stderr, when no
# engine can be had. The engine is left running (log: /var/log/crestereo-dockerd.log).
set -euo pipefail

if [ "${1:-}" = --install ]; then
    missing=()
    command -v dockerd >/dev/null || missing+=(docker.io)
    command -v debootstrap >/dev/null || missing+=(debootstrap)
    command -v docker-compose >/dev/null || missing+=(docker-compose)
    if [ ${#missing[@]} -gt 0 ]; then
        echo "installing ${missing[*]} ..."
        apt-get update -qq
        DEBIAN_FRONTEND=noninteractive apt-get install -y -qq --no-install-recommends \
            "${missing[@]}" ca-certificates >/dev/null
    fi
fi

docker info >/dev/null 2>&1 && exit 0

command -v docker >/dev/null || { echo "no docker client installed" >&2; exit 1; }
command -v dockerd >/dev/null || { echo "no Docker engine (dockerd) installed; Debian: apt-get install docker.io" >&2; exit 1; }
[ "$(id -u)" = 0 ] || { echo "dockerd is not running and only root can start it here" >&2; exit 1; }

log=/var/log/crestereo-dockerd.log
echo "starting dockerd (log: $log) ..."
setsid nohup dockerd >"$log" 2>&1 </dev/null &
for _ in $(seq 60); do
    docker info >/dev/null 2>&1 && exit 0
    sleep 0.5
done
echo "dockerd did not come up within 30 s; its log ends with:" >&2
tail -n 20 "$log" >&2
exit 1
