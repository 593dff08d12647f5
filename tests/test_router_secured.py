"""``glider-hil router --config`` with the secured configuration of config/zenoh/ (TLS,
users and passwords, access control): the service publishes through it, an authenticated
observer reads, and ``fleet`` with the observer's configuration lists the vehicle."""

from __future__ import annotations

import json
import shutil

import pytest

from hil_service.cli.processes import run_verb, wait_for_line
from hil_service.cli.router import ROUTER_READY
from tests.conftest import free_tcp_port, free_udp_port
from tests.test_zenoh_security import _install_configs
from tests.zenoh_peer import ZenohProbe

pytestmark = pytest.mark.skipif(shutil.which("openssl") is None, reason="needs the openssl CLI")


@pytest.mark.timeout(180)
def test_router_verb_runs_the_secured_configuration(processes, tmp_path) -> None:
    configs = _install_configs(tmp_path)
    endpoint = f"tls/127.0.0.1:{free_tcp_port()}"
    router = processes.start("router", "--config", str(configs["router"]), "--listen", endpoint)
    wait_for_line(router, ROUTER_READY, 30)
    udp = free_udp_port()
    processes.start_service(
        "--mavlink", f"udpin:127.0.0.1:{udp}", "--zenoh-config", str(configs["service"]),
        "--zenoh-connect", endpoint, "--no-log",
    )  # fmt: skip
    processes.start(
        "emulate", "--connect", f"udpout:127.0.0.1:{udp}", "--speed", "50",
        "--duration", "100000", "--scenario", "paper", "--seed", "3",
    )  # fmt: skip
    observer = ZenohProbe(endpoint, config_file=str(configs["observer"]))
    try:
        assert observer.wait_for(lambda: observer.count("glider/1/health") > 0, 60)
    finally:
        observer.close()
    result = run_verb(
        "fleet",
        "--zenoh-config",
        str(configs["observer"]),
        "--zenoh-connect",
        endpoint,
        "--json",
        timeout=60,
    )
    assert result.returncode == 0, result.stderr
    vehicles = json.loads(result.stdout)["vehicles"]
    assert [v["system_id"] for v in vehicles] == [1], vehicles
    assert vehicles[0]["link_rate"] > 0
