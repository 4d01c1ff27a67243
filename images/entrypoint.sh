#!/bin/bash
# Entrypoint of the fleetctl images.
#
# When WG_CONFIG names a wg-quick style config written by `fleetctl` (wg0.conf), bring the
# tunnel up with wireguard-go (userspace: the kernels here have no WireGuard module). That
# needs root, cap NET_ADMIN and /dev/net/tun; without them we say so loudly and go on over the
# plain network (WG_REQUIRED=1 makes it fatal instead). Then drop to the unprivileged
# `fleetctl` user (when started as root) and exec the command.
set -euo pipefail

log() { echo "fleetctl-entrypoint: $*" >&2; }

# The values of key $1 in wg-quick config $2, one per line, as written.
conf_values() { sed -n "s/^[[:space:]]*$1[[:space:]]*=[[:space:]]*//p" "$2"; }

# The sockets bound to UDP port $1 in this network namespace (ss's lines; empty: free).
udp_port_holders() { ss -Huanp "sport = :$1" 2>/dev/null || true; }

# wg setconf, and once more after a conflict on the listen port has gone. Once in 15
# e2e fleet starts the server's wg setconf failed with "Address already in use" in a new
# network namespace, where nothing of ours binds that port, and what did was not known.
# Now the log names the holder (ss), and one that lets go within 3 s is waited out
# instead of stopping the server.
wg_setconf() {
  local iface=$1 stripped=$2 port=$3 err i
  if err=$(wg setconf "$iface" <(printf '%s\n' "$stripped") 2>&1); then
    return 0
  fi
  printf '%s\n' "$err" >&2
  case $err in *"Address already in use"*) ;; *) return 1 ;; esac
  [[ $port =~ ^[0-9]+$ ]] || return 1
  log "WARNING: UDP port $port is taken in this network namespace by: $(udp_port_holders "$port" | tr -s ' \n' ' ')"
  for i in $(seq 30); do
    [ -z "$(udp_port_holders "$port")" ] && break
    sleep 0.1
  done
  if wg setconf "$iface" <(printf '%s\n' "$stripped"); then
    log "UDP port $port free again; wg setconf applied on the second attempt"
    return 0
  fi
  return 1
}

wg_up() {
  local conf=$1 iface
  iface=$(basename "$conf" .conf)
  if [ "$(id -u)" != 0 ] || [ ! -c /dev/net/tun ]; then
    log "WARNING: WireGuard unavailable (need root, NET_ADMIN and /dev/net/tun); $conf NOT used, running over the plain network"
    return 1
  fi
  WG_PROCESS_FOREGROUND=1 wireguard-go -f "$iface" >/tmp/wireguard-go.log 2>&1 &
  # Wait (bounded, 5 s) for the UAPI socket instead of guessing a delay.
  local i
  for i in $(seq 50); do
    [ -S "/var/run/wireguard/$iface.sock" ] && break
    sleep 0.1
  done
  if [ ! -S "/var/run/wireguard/$iface.sock" ]; then
    log "WARNING: wireguard-go did not start: $(tail -3 /tmp/wireguard-go.log)"
    return 1
  fi
  # Every step is checked by hand: wg_up runs as the condition of an `if`, where bash
  # ignores `set -e`. A config wg could not apply (a peer's key mistyped in a hand edit)
  # was logged, then "WireGuard wg0 up" and a healthy server without peers, even with
  # WG_REQUIRED=1.
  local stripped addr mtu allowed port
  if ! stripped=$(wg-quick strip "$conf"); then
    log "WARNING: wg-quick strip $conf failed (above)"
    return 1
  fi
  port=$(conf_values ListenPort "$conf" | head -1)
  if ! wg_setconf "$iface" "$stripped" "$port"; then
    log "WARNING: $conf: wg setconf refused it (above)"
    return 1
  fi
  for addr in $(conf_values Address "$conf" | tr ',' ' '); do
    if ! ip address add "$addr" dev "$iface"; then
      log "WARNING: $conf: cannot give $iface the address $addr (above)"
      return 1
    fi
  done
  mtu=$(conf_values MTU "$conf" | head -1)
  if ! ip link set "$iface" mtu "${mtu:-1380}" up; then
    log "WARNING: $conf: cannot bring $iface up with MTU ${mtu:-1380} (above)"
    return 1
  fi
  for allowed in $(conf_values AllowedIPs "$conf" | tr ',' ' '); do
    ip route replace "$allowed" dev "$iface" 2>/dev/null || true
  done
  log "WireGuard $iface up: $(ip -brief address show "$iface")"
}

if [ -n "${WG_CONFIG:-}" ]; then
  if [ ! -r "$WG_CONFIG" ]; then
    log "WARNING: WG_CONFIG=$WG_CONFIG is not readable; running over the plain network"
    [ "${WG_REQUIRED:-0}" = 1 ] && exit 78
  elif ! wg_up "$WG_CONFIG"; then
    [ "${WG_REQUIRED:-0}" = 1 ] && { log "WG_REQUIRED=1: giving up"; exit 78; }
  fi
fi

# FLEETCTL_SECRETS names a read-only directory of secret files (the TLS key) that the
# unprivileged process must read: copy them, as root, into a 0700 directory it owns, each 0600.
# The host's copies stay 0600 root-owned; nothing is ever made world-readable.
hand_over_secrets() {
  local src=$1 dst=/run/fleetctl/secrets f
  install -d -m 0700 /run/fleetctl "$dst"
  for f in "$src"/*; do
    [ -f "$f" ] || continue
    install -m 0600 "$f" "$dst/$(basename "$f")"
  done
  if [ "$(id -u)" = 0 ] && id fleetctl >/dev/null 2>&1; then
    chown -R fleetctl:fleetctl /run/fleetctl
  fi
}

if [ -n "${FLEETCTL_SECRETS:-}" ]; then
  hand_over_secrets "$FLEETCTL_SECRETS"
fi

if [ "$(id -u)" = 0 ] && [ "${RUN_AS_ROOT:-0}" != 1 ] && id fleetctl >/dev/null 2>&1; then
  # setpriv changes the ids, not the environment: without this HOME stays /root and ROS
  # (rcl logging in ~/.ros/log) cannot start.
  HOME=$(getent passwd fleetctl | cut -d: -f6)
  export HOME USER=fleetctl LOGNAME=fleetctl
  exec setpriv --reuid=fleetctl --regid=fleetctl --init-groups --inh-caps=-all "$@"
fi
exec "$@"
