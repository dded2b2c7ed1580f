# socd: the battery state estimator service.
#
#   docker build -t socd .
#   docker run --rm --network host \
#       -v /etc/socd:/config:ro -v socd-state:/state \
#       socd
#
# The config is mounted at /config/socd.toml (read-only is fine).  Put the checkpoint on a
# writable volume:  [checkpoint] path = "/state/socd.ckpt".
#
# --network host: SocketCAN interfaces (can0, vcan0) live in the host's network namespace;
# a container on the default bridge network cannot see them.  Bring the link up on the
# host first (see deploy/socd.service).  Host networking also lets a dashboard reach the
# Zenoh endpoint; the default config listens on tcp/127.0.0.1:7447 only: set
# [zenoh] listen explicitly (e.g. to the host's CAN-side address) to expose it further.
#
# The DBCs and the cell profile ship in the image under /opt/socd; a mounted config that
# uses its own should give absolute paths (relative ones resolve against /config):
#   cell_profile = "/opt/socd/configs/cells/panasonic_18650pf.toml"
#   [dbc]  input = "/opt/socd/dbc/bms_pack.dbc"   output = "/opt/socd/dbc/socd_output.dbc"
FROM python:3.11-slim

ENV PYTHONDONTWRITEBYTECODE=1 \
    PYTHONUNBUFFERED=1 \
    PIP_NO_CACHE_DIR=1 \
    PIP_DISABLE_PIP_VERSION_CHECK=1

WORKDIR /opt/socd
COPY pyproject.toml README.md* ./
COPY service ./service
COPY replay ./replay
COPY dbc ./dbc
COPY configs ./configs
RUN pip install . \
    && useradd --system --uid 10001 --home-dir /nonexistent --shell /usr/sbin/nologin socd \
    && mkdir -p /config /state \
    && chown socd /state

USER socd
VOLUME ["/state"]
ENTRYPOINT ["socd", "run", "--config", "/config/socd.toml"]
