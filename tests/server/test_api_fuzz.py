"""The API against its own OpenAPI document (schemathesis), on a bounded budget.

Every operation of the app as production builds it (station 1 on SQLite, three stored
measurements, no station process: the station routes answer 503 after auth), with every
schemathesis check: no 5xx, every status, media type, header and body as documented, invalid
input refused, auth enforced, 405 with Allow for undeclared methods.
"""

from __future__ import annotations

import os
from pathlib import Path

import numpy as np
import pytest
import schemathesis
from apps import ENGINEER, settings
from hypothesis import HealthCheck
from hypothesis import settings as budget
from records import make_record
from schemathesis.config import SchemathesisConfig
from schemathesis.specs.openapi.schemas import OpenApiSchema

from mvpose_core.reasons import Reason
from server.app import create_app
from server.state import open_services

#: examples per operation and phase: the whole module stays well under 60 s; a deeper run:
#: MVPOSE_FUZZ_EXAMPLES=100 pytest --timeout 1800 tests/server/test_api_fuzz.py
MAX_EXAMPLES = int(os.environ.get("MVPOSE_FUZZ_EXAMPLES", "5"))

# Where the schema cannot say everything that makes a request valid, a schema-valid request may
# be refused with a documented 4xx: an opaque cursor this API did not hand out (400), a recipe
# that is a JSON object but not a valid recipe (400) or does not fit the station (422), an empty
# calibration (400), a gauge study whose selection cannot make the study (400). Without a
# station process the station routes, a measuring verify and the hand-eye steps answer 503
# (documented).
ACCEPTED = '"2xx", "3xx", "401", "403", "404", "409", "429", "5xx"'  # schemathesis' default
CONFIG = f"""
# the engineer's token through the document's security scheme, so that cases without it
# (schemathesis drops it to check auth) are sent without it
[auth.openapi.HTTPBearer]
bearer = "{ENGINEER}"
[[operations]]
include-name = "GET /api/v1/measurements"
checks.positive_data_acceptance.expected-statuses = [{ACCEPTED}, "400"]

[[operations]]
include-name = ["POST /api/v1/recipes/{{name}}/versions",
                "POST /api/v1/calibrations/{{name}}/versions"]
checks.positive_data_acceptance.expected-statuses = [{ACCEPTED}, "400", "422"]

[[operations]]
include-name = "POST /api/v1/gauge/studies"
checks.positive_data_acceptance.expected-statuses = [{ACCEPTED}, "400"]

[[operations]]
include-path-regex = "^/api/v1/(station/|calibration/verify$|calibration/handeye)"
checks.not_a_server_error.expected-statuses = ["2xx", "3xx", "4xx", "503"]
"""


@pytest.fixture(scope="module")
def seeded_schema(tmp_path_factory: pytest.TempPathFactory) -> OpenApiSchema:
    config = settings(Path(tmp_path_factory.mktemp("fuzz")))
    services = open_services(config)  # stored as the pipeline stores them
    try:
        rng = np.random.default_rng(7)
        for i, reason in enumerate([Reason.OK, Reason.MARKS_MISSING, Reason.OK], start=1):
            services.record_measurement(
                make_record(rng, services.station_name, trigger_id=i, reason=reason))
    finally:
        services.close()
    loaded = schemathesis.openapi.from_asgi(
        "/openapi.json", create_app(config), config=SchemathesisConfig.from_str(CONFIG))
    # the token is configured for the document's own security scheme (a name that matched
    # nothing would leave every case a quiet 401)
    assert set(loaded.auth_schemes) == set(loaded.raw_schema["components"]["securitySchemes"])
    return loaded


@pytest.fixture
def api_schema(request: pytest.FixtureRequest, seeded_schema: OpenApiSchema) -> OpenApiSchema:
    # schemathesis 4.32's lazy loader renames the test through ``node._nodeid``, which pytest 9
    # no longer has: give it the id it expects.
    if not hasattr(request.node, "_nodeid"):
        request.node._nodeid = request.node.nodeid
    return seeded_schema


schema = schemathesis.pytest.from_fixture("api_schema")


@schema.parametrize()
# derandomized: the suite runs the same cases every time (a failure reproduces; none appears
# by chance in CI); MVPOSE_FUZZ_EXAMPLES explores further
@budget(max_examples=MAX_EXAMPLES, deadline=None, derandomize=True, database=None,
        suppress_health_check=list(HealthCheck))
def test_every_operation_answers_as_documented(case: schemathesis.Case) -> None:
    response = case.call_and_validate()
    if response.request.headers.get("Authorization") == f"Bearer {ENGINEER}":
        assert response.status_code != 401, response.text
