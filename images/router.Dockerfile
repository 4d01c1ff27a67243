# The e2e router: forwards between the robot network and the server network and shapes each
# direction with tc on its egress interface. Needs cap_add NET_ADMIN; runs as root because
# tc and sysctl need it. The base has iproute2 (tc, ip) and python3 (the health check).
ARG BASE_IMAGE=fleetctl/base:bookworm
FROM ${BASE_IMAGE}
ARG VERSION=0.0.0
LABEL org.opencontainers.image.title="fleetctl-router" \
      org.opencontainers.image.description="fleetctl e2e link shaper (tc tbf/htb/netem)" \
      org.opencontainers.image.version="${VERSION}"
COPY healthcheck.py /usr/local/bin/fleetctl-healthcheck
ENV FLEETCTL_HEALTH=forwarding
HEALTHCHECK --interval=5s --timeout=3s --retries=3 \
  CMD ["python3", "/usr/local/bin/fleetctl-healthcheck"]
# PID 1 waits for a signal; the e2e runner drives tc with docker exec.
CMD ["python3", "-c", "import signal; signal.sigwait({signal.SIGTERM, signal.SIGINT})"]
