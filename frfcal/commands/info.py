"""``frfcal info``: what this installation can drive, and what hardware it can see.

Each probe is guarded: a missing extra, a missing NI-DAQmx runtime or a VISA
backend without resources gives a one-line "not installed" / "not found"
message, never a traceback.
"""

from __future__ import annotations

import argparse

HELP = "list installed drivers (sim, visa, ni), sparse factorization backends, VISA resources and NI-DAQmx devices"

PACKAGES = ("numpy", "scipy", "pyNastran", "h5py", "pyuff", "matplotlib", "pydantic",
            "pyvisa", "pyvisa-py", "nidaqmx", "dask", "distributed", "cholespy", "pypardiso", "scikit-sparse")


def configure(parser: argparse.ArgumentParser) -> None:
    parser.add_argument("--json", action="store_true", help="print one JSON object")
    parser.add_argument("--visa-backend", default="@py", metavar="B",
                        help="pyvisa backend to list resources with ('@py' = pyvisa-py, '' = system VISA)")
    parser.add_argument("--no-scan", action="store_true", help="skip the VISA resource scan (it may take seconds)")
    parser.add_argument("--probe", action="append", default=[], metavar="RESOURCE",
                        help="ask this VISA resource for *IDN? (e.g. TCPIP::192.168.0.20::5025::SOCKET); repeatable")
    parser.add_argument("--hardware", metavar="HW.toml",
                        help="check a hardware configuration file: probe its VISA instruments / NI devices")
    parser.add_argument("--timeout-ms", type=int, default=2000, help="timeout of each *IDN? probe (ms)")
    parser.add_argument("--hardware-template", metavar="LAYOUT.json",
                        help="print a hardware TOML skeleton for the channels of a pretest layout and exit")
    parser.add_argument("--template-driver", choices=("ni", "visa"), default="ni",
                        help="driver section of the skeleton (default ni)")


def _version(dist: str) -> str | None:
    from importlib import metadata

    try:
        return metadata.version(dist)
    except metadata.PackageNotFoundError:
        return None


def _drivers() -> dict:
    out = {"sim": {"available": True, "detail": "built in (acquisition.SimulatedLab)"}}
    pv, pvp = _version("pyvisa"), _version("pyvisa-py")
    if pv is None:
        out["visa"] = {"available": False, "detail": "not installed: pip install 'frfcal[visa]'"}
    else:
        detail = f"pyvisa {pv}" + (f", pyvisa-py {pvp}" if pvp else " (pyvisa-py not installed: only a system VISA backend)")
        out["visa"] = {"available": True, "detail": detail}
    nv = _version("nidaqmx")
    if nv is None:
        out["ni"] = {"available": False, "detail": "not installed: pip install 'frfcal[ni]'"}
    else:
        runtime = _ni_runtime()
        out["ni"] = {"available": runtime["found"], "detail": f"nidaqmx {nv}; " + runtime["detail"]}
    return out


def _sparse_backends() -> dict:
    """The sparse factorization backends (femodel.factorize) and the one in use."""
    import os

    from femodel import FactorizationError, available_backends, default_backend
    from femodel._factor import ENV_VAR

    backends = {b.name: {"available": b.available, "detail": b.detail} for b in available_backends()}
    try:
        in_use, problem = default_backend(), None
    except FactorizationError as exc:  # the env var names a missing or unknown backend
        in_use, problem = None, str(exc)
    return {"in_use": in_use, "forced_by": f"{ENV_VAR}={os.environ[ENV_VAR]}" if os.environ.get(ENV_VAR) else None,
            "problem": problem, "backends": backends}


def _ni_runtime() -> dict:
    try:
        import nidaqmx.system
        from nidaqmx.errors import DaqNotFoundError

        system = nidaqmx.system.System.local()
        v = system.driver_version
        return {"found": True, "detail": f"NI-DAQmx runtime {v.major_version}.{v.minor_version}.{v.update_version}"}
    except ImportError as exc:
        return {"found": False, "detail": f"nidaqmx cannot be imported: {exc}"}
    except DaqNotFoundError:
        return {"found": False, "detail": "NI-DAQmx runtime not installed (the driver needs NI's DAQmx library)"}
    except Exception as exc:  # noqa: BLE001 - any failure of a vendor library is reported, not raised
        return {"found": False, "detail": f"NI-DAQmx runtime unusable: {type(exc).__name__}: {exc}"}


def _ni_devices() -> dict:
    if _version("nidaqmx") is None:
        return {"ok": False, "detail": "nidaqmx not installed", "devices": []}
    try:
        import nidaqmx.system

        devices = [
            {"name": d.name, "product_type": d.product_type, "serial": f"{d.dev_serial_num:X}"}
            for d in nidaqmx.system.System.local().devices
        ]
        return {"ok": True, "detail": f"{len(devices)} device(s)", "devices": devices}
    except Exception as exc:  # noqa: BLE001
        from nidaqmx.errors import DaqNotFoundError

        if isinstance(exc, DaqNotFoundError):
            return {"ok": False, "detail": "NI-DAQmx runtime not installed", "devices": []}
        return {"ok": False, "detail": f"{type(exc).__name__}: {exc}", "devices": []}


def _visa_manager(backend: str):
    import pyvisa

    return pyvisa.ResourceManager(backend)


def _visa_resources(backend: str) -> dict:
    if _version("pyvisa") is None:
        return {"ok": False, "detail": "pyvisa not installed", "resources": []}
    import warnings

    try:
        with warnings.catch_warnings():
            warnings.simplefilter("ignore")
            rm = _visa_manager(backend)
            try:
                found = list(rm.list_resources("?*::INSTR"))
            finally:
                rm.close()
        return {"ok": True, "detail": f"{len(found)} resource(s) via backend {backend or 'system VISA'!r}",
                "resources": found}
    except Exception as exc:  # noqa: BLE001
        return {"ok": False, "detail": f"VISA backend {backend!r} unusable: {type(exc).__name__}: {exc}",
                "resources": []}


def _probe(backend: str, resources: list[str], timeout_ms: int) -> list[dict]:
    if not resources:
        return []
    if _version("pyvisa") is None:
        return [{"resource": r, "ok": False, "reply": "pyvisa not installed"} for r in resources]
    from acquisition import DriverError
    from acquisition._scpi import ScpiReplyError, parse_idn
    from acquisition.drivers.visa import VisaInstrument

    out = []
    rm = _visa_manager(backend)
    try:
        for r in resources:
            inst = VisaInstrument(rm, r, r, timeout_ms)
            try:
                out.append({"resource": r, "ok": True, "reply": inst.query("*IDN?", parse_idn)})
            except (DriverError, ScpiReplyError) as exc:
                out.append({"resource": r, "ok": False, "reply": str(exc)})
            finally:
                inst.close()
    finally:
        rm.close()
    return out


def _check_hardware(path: str, backend: str, timeout_ms: int, ni_devices: list[dict]) -> dict:
    from acquisition._hardware_config import read_hardware_config
    from acquisition.drivers.ni import device_of

    hw = read_hardware_config(path)
    result = {"path": path, "driver": hw.driver, "channels": len(hw.channels), "problems": []}
    if hw.driver == "visa" or (hw.driver is None and hw.visa):
        resources = [hw.visa.get("generator", "")] + [c.physical for c in hw.channels.values()]
        result["probes"] = _probe(hw.visa.get("backend", backend), [r for r in resources if r], timeout_ms)
        result["problems"] += [f"{p['resource']}: {p['reply']}" for p in result["probes"] if not p["ok"]]
    if hw.driver == "ni" or (hw.driver is None and hw.ni):
        names = {d["name"] for d in ni_devices}
        wanted = sorted({device_of(c.physical) for c in hw.channels.values()}
                        | ({device_of(hw.ni["ao_channel"])} if "ao_channel" in hw.ni else set()))
        result["ni_devices_needed"] = wanted
        result["problems"] += [f"NI device {d!r} not present" for d in wanted if d not in names]
    return result


def run(args) -> int:
    import json
    import platform

    from frfcal import __version__

    if args.hardware_template:
        from acquisition import read_layout
        from acquisition._hardware_config import hardware_template

        layout = read_layout(args.hardware_template)
        print(hardware_template(layout.sensors + layout.drives, args.template_driver))
        return 0
    ni = _ni_devices()
    report = {
        "frfcal": __version__,
        "python": platform.python_version(),
        "packages": {p: _version(p) for p in PACKAGES},
        "drivers": _drivers(),
        "sparse": _sparse_backends(),
        "visa": {"ok": False, "detail": "scan skipped (--no-scan)", "resources": []}
        if args.no_scan else _visa_resources(args.visa_backend),
        "ni": ni,
        "probes": _probe(args.visa_backend, list(args.probe), args.timeout_ms),
    }
    if args.hardware:
        report["hardware"] = _check_hardware(args.hardware, args.visa_backend, args.timeout_ms, ni["devices"])
    if args.json:
        print(json.dumps(report, indent=2))
        return 0
    print(f"frfcal {report['frfcal']} (Python {report['python']})")
    print("packages: " + ", ".join(f"{k} {v}" if v else f"{k} (not installed)" for k, v in report["packages"].items()))
    print("drivers:")
    for name, d in report["drivers"].items():
        print(f"  {name:5s} {'available' if d['available'] else 'unavailable':11s} {d['detail']}")
    sparse = report["sparse"]
    if sparse["in_use"]:
        forced = f" ({sparse['forced_by']})" if sparse["forced_by"] else ""
        print(f"sparse factorization: {sparse['in_use']}{forced}")
    else:
        print(f"sparse factorization: unusable setting: {sparse['problem']}")
    for name, d in sparse["backends"].items():
        print(f"  {name:8s} {'available' if d['available'] else 'unavailable':11s} {d['detail']}")
    v = report["visa"]
    print(f"VISA resources: {v['detail']}")
    for r in v["resources"]:
        print(f"  {r}")
    print(f"NI-DAQmx devices: {ni['detail']}")
    for d in ni["devices"]:
        print(f"  {d['name']}: {d['product_type']} (serial {d['serial']})")
    for p in report["probes"]:
        print(f"probe {p['resource']}: {'OK ' if p['ok'] else 'FAILED '}{p['reply']}")
    if args.hardware:
        h = report["hardware"]
        print(f"hardware file {h['path']}: driver {h['driver']}, {h['channels']} channel(s)")
        for p in h.get("probes", []):
            print(f"  {p['resource']}: {'OK ' if p['ok'] else 'FAILED '}{p['reply']}")
        for problem in h["problems"]:
            print(f"  problem: {problem}")
        if not h["problems"]:
            print("  no problems found")
    return 0
