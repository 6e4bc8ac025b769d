# Local stand-in for python:3.11-slim-bookworm, built by make-base-image.sh on top of a
# debootstrapped (minbase) Debian bookworm root filesystem. Debian's python3 is 3.11 on bookworm.
ARG ROOTFS=crestereo-local/debian:bookworm-minbase
FROM ${ROOTFS}

ARG DEBIAN_FRONTEND=noninteractive
ENV LANG=C.UTF-8

# Versions come from the bookworm suites with their security updates (debootstrap installs the
# release's versions, hence the upgrade), as in the public image.
# hadolint ignore=DL3005,DL3008
RUN apt-get update \
    && apt-get upgrade -y \
    && apt-get install -y --no-install-recommends ca-certificates python3 python3-venv \
    && rm -rf /var/lib/apt/lists/* /var/cache/debconf/*-old \
    && ln -s /usr/bin/python3 /usr/local/bin/python \
    && python3 --version

CMD ["python3"]
