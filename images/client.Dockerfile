# fleetctl robot client (a ROS 2 Jazzy node, rclpy from PyPI wheels) and the simulated robot.
# The ROS wheelhouse is installed in its own layer before the code, so a code change does not
# reinstall ROS.
ARG BASE_IMAGE=fleetctl/base:bookworm

FROM ${BASE_IMAGE} AS deps
COPY wheels/base /wheels/base
RUN python3 -m venv /opt/fleetctl \
 && /opt/fleetctl/bin/pip install --no-index --no-cache-dir -q /wheels/base/*.whl
COPY wheels/ros /wheels/ros
RUN /opt/fleetctl/bin/pip install --no-index --no-cache-dir -q --find-links /wheels/base /wheels/ros/*.whl
# Eclipse Zenoh: the e2e `peer` scenario's baseline (not used by fleetctl itself).
COPY wheels/peers /wheels/peers
RUN if ls /wheels/peers/*.whl >/dev/null 2>&1; then \
      /opt/fleetctl/bin/pip install --no-index --no-deps --no-cache-dir -q /wheels/peers/*.whl; \
    fi
# tf2_msgs and foxglove_msgs, built by `fleetctl build` (none on PyPI); may be empty.
COPY wheels/rosmsgs /wheels/rosmsgs
RUN if ls /wheels/rosmsgs/*.whl >/dev/null 2>&1; then \
      /opt/fleetctl/bin/pip install --no-index --no-deps --no-cache-dir -q /wheels/rosmsgs/*.whl; \
    fi

FROM ${BASE_IMAGE}
ARG VERSION=0.0.0
LABEL org.opencontainers.image.title="fleetctl-client" \
      org.opencontainers.image.description="fleetctl ROS 2 robot client and simulated robot" \
      org.opencontainers.image.version="${VERSION}"
RUN useradd --system --uid 10001 --user-group --create-home --home-dir /var/lib/fleetctl fleetctl
COPY --from=deps /opt/fleetctl /opt/fleetctl
COPY wheels/app /wheels/app
RUN /opt/fleetctl/bin/pip install --no-index --no-deps --no-cache-dir -q /wheels/app/*.whl \
 && rm -rf /wheels
COPY entrypoint.sh /usr/local/bin/fleetctl-entrypoint
COPY healthcheck.py /usr/local/bin/fleetctl-healthcheck
# AMENT_PREFIX_PATH lets ament_index find the message packages the wheels installed.
ENV PATH=/opt/fleetctl/bin:$PATH PYTHONUNBUFFERED=1 AMENT_PREFIX_PATH=/opt/fleetctl \
    FLEETCTL_HEALTH=process:fleetctl
WORKDIR /var/lib/fleetctl
# WireGuard (wireguard-go) needs root + NET_ADMIN + /dev/net/tun: compose runs this image as
# root when a WG_CONFIG is given; the entrypoint brings the tunnel up, then drops to fleetctl.
USER fleetctl
HEALTHCHECK --interval=5s --timeout=3s --start-period=10s --retries=3 \
  CMD ["python3", "/usr/local/bin/fleetctl-healthcheck"]
ENTRYPOINT ["/usr/local/bin/fleetctl-entrypoint"]
CMD ["fleetctl", "client", "--config", "/etc/fleetctl/robot/client.yaml"]
