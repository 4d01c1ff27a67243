"""A compose service, as :mod:`fleetctl.deploy.compose` renders it, turned into ``docker run``
arguments.

``fleetctl e2e`` starts the server from the very service ``fleetctl up`` deploys
(:func:`fleetctl.deploy.compose.server_service`), in its own networks and without Compose.
The conversion is strict: a key it does not know raises instead of being skipped, so a new
setting in the deployment is either carried into e2e or noticed, never silently dropped.

Compose file format 2.4 keys (https://docs.docker.com/reference/compose-file/legacy-versions/)
and the ``docker run`` option each becomes:

=============  ==========================================================================
``image``      the image argument
``command``    the arguments after the image (a list; a string would need a shell's
               splitting, so it is refused)
``user``       ``--user``
``environment``  ``--env KEY=VALUE`` (mapping or ``KEY=VALUE`` list; a ``None`` value
               passes the caller's own, as Compose does)
``volumes``    ``--volume`` (short syntax; a named volume must be mapped by the caller)
``ports``      ``--publish``
``restart``    ``--restart``
``cap_add``    ``--cap-add``
``devices``    ``--device``
``networks``   ``--network`` (exactly one: ``docker run`` attaches one network),
               ``ipv4_address`` -> ``--ip``, ``aliases`` -> ``--network-alias``
``labels``     ``--label``
``extra_hosts``  ``--add-host``
=============  ==========================================================================

``depends_on`` has no ``docker run`` equivalent (ordering is the caller's job): it is refused
like any other unknown key.
"""

from __future__ import annotations

from collections.abc import Mapping, Sequence
from typing import Any

from fleetctl.errors import FleetError

_FLAGS = {"user": "--user", "restart": "--restart"}
_LISTS = {"ports": "--publish", "cap_add": "--cap-add", "devices": "--device",
          "extra_hosts": "--add-host"}
_HANDLED = {"image", "command", "environment", "volumes", "networks", "labels", *_FLAGS,
            *_LISTS}


def run_args(service: Mapping[str, Any], *, name: str, networks: Mapping[str, str],
             volumes: Mapping[str, str | None] | None = None,
             extra: Sequence[str] = ()) -> list[str]:
    """``docker run`` arguments for *service* (everything after ``docker run``).

    The result starts with ``--detach --name NAME``, then the service's options, then
    *extra*, the image and the command.

    Args:
        service: One compose service (format 2.4 keys, see the module doc).
        name: The container's name.
        networks: Compose network name -> the Docker network to attach instead.
        volumes: Compose named volume -> the Docker volume to mount instead; ``None``: an
            anonymous volume (``docker rm --volumes`` removes it with the container).
            ``None`` for the whole mapping: no named volumes allowed.
        extra: More ``docker run`` options (the caller's labels, aliases, ...).

    Raises:
        FleetError: an unknown key, a string command, no image, not exactly one network,
            a network or named volume the caller did not map.
    """
    unknown = sorted(set(service) - _HANDLED)
    if unknown:
        raise FleetError(f"compose service for {name}: no `docker run` conversion for {unknown}")
    image = service.get("image")
    if not isinstance(image, str) or not image:
        raise FleetError(f"compose service for {name}: no image")
    argv = ["--detach", "--name", name]
    for key, flag in _FLAGS.items():
        if service.get(key) is not None:
            argv += [flag, str(service[key])]
    for key, flag in _LISTS.items():
        argv += [arg for item in _list(service, key, name) for arg in (flag, str(item))]
    argv += [arg for kv in _pairs(service.get("environment"), name)
             for arg in ("--env", kv)]
    argv += [arg for kv in _pairs(service.get("labels"), name) for arg in ("--label", kv)]
    for spec in _list(service, "volumes", name):
        argv += ["--volume", _volume(str(spec), volumes or {}, volumes is None, name)]
    argv += _network(service.get("networks"), networks, name)
    return [*argv, *extra, image, *_command(service.get("command"), name)]


def _list(service: Mapping[str, Any], key: str, name: str) -> list[Any]:
    value = service.get(key) or []
    if not isinstance(value, list):
        raise FleetError(f"compose service for {name}: {key} must be a list, not {value!r}")
    return value


def _pairs(value: Any, name: str) -> list[str]:
    """``KEY=VALUE`` strings of a compose mapping or list (``None`` value: ``KEY`` alone)."""
    if value is None:
        return []
    if isinstance(value, list):
        return [str(v) for v in value]
    if not isinstance(value, Mapping):
        raise FleetError(f"compose service for {name}: expected a mapping or list: {value!r}")
    return [str(k) if v is None else f"{k}={_scalar(v)}" for k, v in value.items()]


def _scalar(value: Any) -> str:
    # Compose writes YAML booleans in environment values as "true"/"false".
    return str(value).lower() if isinstance(value, bool) else str(value)


def _command(value: Any, name: str) -> list[str]:
    if value is None:
        return []
    if not isinstance(value, list):
        raise FleetError(f"compose service for {name}: command must be a list of arguments "
                         f"(a string would need a shell to split it): {value!r}")
    return [str(v) for v in value]


def _volume(spec: str, named: Mapping[str, str | None], strict: bool, name: str) -> str:
    source, sep, rest = spec.partition(":")
    if not sep or source.startswith(("/", ".", "~")):
        return spec  # a bind mount, or an anonymous volume already
    if strict or source not in named:
        raise FleetError(f"compose service for {name}: named volume {source!r} is not mapped")
    target = named[source]
    if target is None:
        return rest.partition(":")[0]  # anonymous: its own, removed with the container
    return f"{target}:{rest}"


def _network(value: Any, mapping: Mapping[str, str], name: str) -> list[str]:
    entries: dict[str, Any] = ({n: None for n in value} if isinstance(value, list)
                               else dict(value or {}))
    if len(entries) != 1:
        raise FleetError(f"compose service for {name}: `docker run` attaches exactly one "
                         f"network, the service names {sorted(entries)}")
    ((network, settings),) = entries.items()
    if network not in mapping:
        raise FleetError(f"compose service for {name}: network {network!r} is not mapped")
    argv = ["--network", mapping[network]]
    settings = settings or {}
    unknown = sorted(set(settings) - {"ipv4_address", "aliases"})
    if unknown:
        raise FleetError(f"compose service for {name}: network settings {unknown} unsupported")
    if settings.get("ipv4_address"):
        argv += ["--ip", str(settings["ipv4_address"])]
    for alias in settings.get("aliases") or []:
        argv += ["--network-alias", str(alias)]
    return argv
