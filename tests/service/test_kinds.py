"""Job kinds: everything kept per kind (typed parameters, job function, maximum runtime) exists for every
kind, and a mapping missing one is refused when its module loads."""

from __future__ import annotations

import pytest

from service.executor import LocalExecutor
from service.job_end import runtime_exceeded
from service.kinds import JobKind, require_every_kind
from service.params import PARAMS_OF_KIND
from service.runner import JOB_FUNCTIONS
from service.settings import MAX_RUNTIME_FIELD, ServiceSettings


def test_a_mapping_missing_a_kind_is_refused_naming_it():
    with pytest.raises(RuntimeError, match="missing job kinds \\['evaluation'\\]"):
        require_every_kind({kind: 1 for kind in JobKind if kind != JobKind.evaluation}, "limits")


@pytest.mark.parametrize("kind", list(JobKind))
def test_every_kind_has_parameters_a_job_function_and_a_maximum_runtime_setting(kind, monkeypatch, tmp_path):
    assert kind in PARAMS_OF_KIND and kind in JOB_FUNCTIONS
    variable = f"SFMNERF_MAX_RUNTIME_{kind.upper()}_MINUTES"
    monkeypatch.setenv(variable, "1.5")
    settings = ServiceSettings(data_dir=tmp_path)
    assert settings.max_runtime_seconds(kind) == 90.0
    assert variable in runtime_exceeded(kind, 90.0)
    assert MAX_RUNTIME_FIELD[kind] in ServiceSettings.model_fields


@pytest.mark.parametrize("kind", list(JobKind))
def test_the_local_supervisor_stops_an_overdue_job_of_every_kind(kind, tmp_path):
    """The supervisor's runtime check for a job of this kind (it raised for evaluation jobs before)."""

    class Process:
        terminated = False

        def terminate(self) -> None:
            self.terminated = True

    class Store:
        def cancel_requested_running(self, _supervisor_id: str) -> list:
            return []

    settings = ServiceSettings(data_dir=tmp_path, **{MAX_RUNTIME_FIELD[kind]: 1.0})
    executor = LocalExecutor(settings, Store())
    running = type("Running", (), {"process": Process(), "kind": str(kind), "started": -1e9,
                                   "stop_reason": None, "terminate_sent_at": None})()  # fmt: skip
    executor._processes["job"] = running
    executor._stop_cancelled_and_overdue()
    assert running.process.terminated and running.stop_reason == runtime_exceeded(kind, 60.0)
