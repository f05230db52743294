"""The job folder layout names the packages' artefacts exactly as the packages write them."""

from __future__ import annotations

from estimation.pipeline import PLY_NAME, REPORT_NAME, TRANSFORMS_NAME
from neural.inference import RUN_CONFIG_FILE
from neural.training import METRICS_FILE
from service.layout import RECONSTRUCTION_EXPORTS, RECONSTRUCTION_REPORT, RUN_CONFIG, RUN_METRICS


def test_the_artefact_names_are_the_packages_own():
    assert RECONSTRUCTION_REPORT == REPORT_NAME
    assert {PLY_NAME, TRANSFORMS_NAME} <= set(RECONSTRUCTION_EXPORTS)
    assert RUN_CONFIG == RUN_CONFIG_FILE
    assert RUN_METRICS == METRICS_FILE
