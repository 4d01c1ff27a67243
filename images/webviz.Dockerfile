# fleetctl web visualizer: static files plus the small server that serves them. three.js and
# Leaflet come from Debian's libjs-three / libjs-leaflet in the base image.
ARG BASE_IMAGE=fleetctl/base:bookworm

FROM ${BASE_IMAGE} AS deps
COPY wheels/base /wheels/base
RUN python3 -m venv /opt/fleetctl \
 && /opt/fleetctl/bin/pip install --no-index --no-cache-dir -q /wheels/base/*.whl

FROM ${BASE_IMAGE}
ARG VERSION=0.0.0
LABEL org.opencontainers.image.title="fleetctl-webviz" \
      org.opencontainers.image.description="fleetctl browser visualizer" \
      org.opencontainers.image.version="${VERSION}"
RUN useradd --system --uid 10001 --user-group --create-home --home-dir /var/lib/fleetctl fleetctl
COPY --from=deps /opt/fleetctl /opt/fleetctl
COPY wheels/app /wheels/app
RUN /opt/fleetctl/bin/pip install --no-index --no-deps --no-cache-dir -q /wheels/app/*.whl \
 && rm -rf /wheels
COPY entrypoint.sh /usr/local/bin/fleetctl-entrypoint
COPY healthcheck.py /usr/local/bin/fleetctl-healthcheck
ENV PATH=/opt/fleetctl/bin:$PATH PYTHONUNBUFFERED=1 FLEETCTL_HEALTH=http://127.0.0.1:8000/
WORKDIR /var/lib/fleetctl
USER fleetctl
EXPOSE 8000
HEALTHCHECK --interval=5s --timeout=3s --start-period=5s --retries=3 \
  CMD ["python3", "/usr/local/bin/fleetctl-healthcheck"]
ENTRYPOINT ["/usr/local/bin/fleetctl-entrypoint"]
# The standard message types only: a fleet with its own mounts FLEET/msg_types read-only
# and adds --fleet to this command (docs/webviz.md, "The fleetctl/webviz image").
CMD ["fleetctl", "webviz", "--host", "0.0.0.0", "--port", "8000"]
