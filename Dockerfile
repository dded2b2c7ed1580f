# socd: the battery state estimator service.
#
#   docker build -t socd .
#   docker run -d --name socd --network host -v socd-state:/var/lib/socd socd
#
# ENTRYPOINT is `socd`; the default command runs the daemon with the packaged example config
# socketcan_can0.toml (SocketCAN can0, the shipped DBCs and cell profile).  Any other
# subcommand works the same way, e.g. `docker run --rm socd demo --seconds 60`.  Your own config:
#
#   docker run -d --network host -v /etc/socd:/etc/socd:ro -v socd-state:/var/lib/socd \
#       socd run --config /etc/socd/socd.toml
#
# Relative paths in that config resolve against /etc/socd; a DBC or cell profile not found there
# is the packaged one of that name (bms_pack.dbc, socd_output.dbc, panasonic_18650pf.toml).
#
# State: /var/lib/socd is a volume owned by the non-root user socd, and STATE_DIRECTORY points
# at it, so a config without [checkpoint] path checkpoints to /var/lib/socd/socd-state.npz.
# The health check is that checkpoint's age: the daemon rewrites it every checkpoint.interval_s
# (30 s by default) once it estimates, so it is unhealthy when it has had no bus data for
# two minutes or cannot write its state (keep interval_s under 120 s).
#
# --network host: SocketCAN interfaces (can0, vcan0) live in the host's network namespace;
# a container on the default bridge network cannot see them.  Bring the link up on the
# host first (see deploy/socd.service).  Host networking also lets a dashboard reach the
# Zenoh endpoint; the example config listens on tcp/127.0.0.1:7447 only: set
# [zenoh] listen explicitly (e.g. to the host's CAN-side address) to expose it further.

FROM python:3.11-slim AS build
ENV PIP_NO_CACHE_DIR=1 PIP_DISABLE_PIP_VERSION_CHECK=1
WORKDIR /src
# service/assets/{dbc,configs,results} link to the top-level dbc/, configs/ and docs/results/: copy all of them
COPY pyproject.toml README.md ./
COPY service ./service
COPY replay ./replay
COPY dbc ./dbc
COPY configs ./configs
COPY docs/results ./docs/results
RUN pip wheel --no-deps --wheel-dir /wheels .

FROM python:3.11-slim
ENV PYTHONDONTWRITEBYTECODE=1 \
    PYTHONUNBUFFERED=1 \
    PIP_NO_CACHE_DIR=1 \
    PIP_DISABLE_PIP_VERSION_CHECK=1 \
    STATE_DIRECTORY=/var/lib/socd
COPY --from=build /wheels /wheels
RUN pip install /wheels/*.whl \
    && rm -rf /wheels \
    && groupadd --system --gid 10001 socd \
    && useradd --system --uid 10001 --gid 10001 --home-dir /nonexistent --shell /usr/sbin/nologin socd \
    && install -d -o socd -g socd -m 0750 /var/lib/socd

# socd:socd by number, so the runtime needs no passwd lookup
USER 10001:10001
VOLUME ["/var/lib/socd"]
HEALTHCHECK --interval=30s --timeout=5s --start-period=2m --retries=3 \
    CMD ["sh", "-c", "find \"$STATE_DIRECTORY/socd-state.npz\" -mmin -2 | grep -q ."]
ENTRYPOINT ["socd"]
CMD ["run", "--config", "socketcan_can0.toml"]
