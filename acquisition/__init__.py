"""Acquisition layer: run files, sweep plans, the stepped-sine controller and drivers."""

from acquisition._driver import (
    ChannelSpec,
    Driver,
    DriverError,
    DriverInfo,
    PhasorBlock,
    SampleBlock,
)

__all__ = ["ChannelSpec", "Driver", "DriverError", "DriverInfo", "PhasorBlock", "SampleBlock"]

from acquisition._controller import (
    AcquisitionAbort,
    LimitBreach,
    OverloadAbort,
    SweepResult,
    plan_channels,
    quantity_of,
    run_plan,
    run_sweep,
)
from acquisition._demod import fit_harmonics, phasors, thd
from acquisition._layout import Layout, LayoutError, read_layout
from acquisition._plan import (
    Plan,
    PlanError,
    Pole,
    estimate_duration_s,
    load_plan,
    plan_from_dict,
    plan_lines,
    summarize_plan,
)
from acquisition._plant import ModalPlant, PlantError
from acquisition._simlab import CubicSpring, Fault, ShakerModel, SimLabError, SimulatedLab
from acquisition._uff import UffError, export_uff, import_uff
from acquisition.runfile import (
    LineQuality,
    Run,
    RunFileError,
    RunWriter,
    create_run,
    read_analysis,
    read_run,
    resume_run,
    write_analysis,
)

__all__ += [
    "AcquisitionAbort",
    "UffError",
    "export_uff",
    "import_uff",
    "LimitBreach",
    "OverloadAbort",
    "Plan",
    "PlanError",
    "Pole",
    "SweepResult",
    "estimate_duration_s",
    "load_plan",
    "plan_channels",
    "plan_from_dict",
    "plan_lines",
    "quantity_of",
    "run_plan",
    "run_sweep",
    "summarize_plan",
    "CubicSpring",
    "Fault",
    "Layout",
    "LayoutError",
    "LineQuality",
    "ModalPlant",
    "PlantError",
    "Run",
    "RunFileError",
    "RunWriter",
    "ShakerModel",
    "SimLabError",
    "SimulatedLab",
    "create_run",
    "fit_harmonics",
    "phasors",
    "read_analysis",
    "read_layout",
    "read_run",
    "resume_run",
    "thd",
    "write_analysis",
]
from acquisition._hardware_config import HardwareConfig, HardwareConfigError, read_hardware_config  # noqa: E402,F401
