"""The calibration campaign: schema, stages with typed results, stored results, outputs (docs/architecture.md).

Application layer: it reads run files (``acquisition``), builds the model
(``femodel``), identifies (``identification``) and calibrates
(``calibration``); the library layers below hold the kernels.
"""

from frfcal.campaign._diagnose import (
    ArticleGate,
    DiagnosisResult,
    LevelRun,
    MemberDiagnosis,
    diagnose_stage,
    member_residual,
    nonlinearity_gate,
    overlay_figure,
    write_diagnosis,
)
from frfcal.campaign._identify import (
    estimated_weights,
    identify_lines,
    identify_run,
    line_weights,
    relative_weights,
    run_weights,
)
from frfcal.campaign._report import json_default, member_figures, write_outputs
from frfcal.campaign._front import LayoutResult, RunFiles, acquire_stage, campaign_plan, import_stage, pretest_stage
from frfcal.campaign._run import (
    FRONT_STAGES,
    LATE_STAGES,
    STAGES,
    StageContext,
    StageSpec,
    campaign_stages,
    load_key,
    model_fingerprint,
    run_campaign,
    section,
    stage_keys,
)
from frfcal.campaign._schema import Campaign, campaign_from_dict, load_campaign
from frfcal.campaign._stages import (
    Article,
    CalibrateResult,
    CrossValidationResult,
    EqualizeResult,
    GroupResult,
    IdentifyResult,
    LoadResult,
    MemberCalibration,
    MemberCrossValidation,
    MemberValidation,
    RunLines,
    Transducer,
    ValidationResult,
    build_model,
    calibrate_stage,
    crossvalidate_stage,
    equalize_stage,
    equalized_data,
    fit_data,
    group_stage,
    identified_modes,
    identify_stage,
    load_stage,
    noise_weights,
    raw_data,
    validate_stage,
)
from frfcal.campaign._store import StageStore, decode, encode, file_hash, fingerprint


def load_articles(camp: Campaign, log=print, identify_data: bool = True) -> list:
    """Every article of the campaign (load stage), identified unless ``identify_data=False``."""
    articles = load_stage(camp, log).articles
    return identified_articles(camp, articles, log) if identify_data else list(articles)


def identified_articles(camp: Campaign, articles, log=print) -> list:
    """``articles`` with their identification attached (identify stage)."""
    return list(identify_stage(camp, articles, log).attached(articles))


__all__ = [
    "FRONT_STAGES",
    "LATE_STAGES",
    "LayoutResult",
    "RunFiles",
    "STAGES",
    "StageContext",
    "StageSpec",
    "acquire_stage",
    "campaign_plan",
    "campaign_stages",
    "import_stage",
    "pretest_stage",
    "section",
    "Article",
    "ArticleGate",
    "DiagnosisResult",
    "LevelRun",
    "MemberDiagnosis",
    "diagnose_stage",
    "member_residual",
    "nonlinearity_gate",
    "overlay_figure",
    "write_diagnosis",
    "CalibrateResult",
    "Campaign",
    "CrossValidationResult",
    "EqualizeResult",
    "GroupResult",
    "IdentifyResult",
    "LoadResult",
    "MemberCalibration",
    "MemberCrossValidation",
    "MemberValidation",
    "RunLines",
    "StageStore",
    "Transducer",
    "ValidationResult",
    "build_model",
    "calibrate_stage",
    "campaign_from_dict",
    "crossvalidate_stage",
    "decode",
    "encode",
    "equalize_stage",
    "equalized_data",
    "file_hash",
    "fingerprint",
    "group_stage",
    "identified_articles",
    "identified_modes",
    "identify_lines",
    "relative_weights",
    "estimated_weights",
    "identify_run",
    "identify_stage",
    "json_default",
    "line_weights",
    "load_articles",
    "load_campaign",
    "load_key",
    "load_stage",
    "member_figures",
    "model_fingerprint",
    "raw_data",
    "fit_data",
    "noise_weights",
    "run_campaign",
    "run_weights",
    "stage_keys",
    "validate_stage",
    "write_outputs",
]
