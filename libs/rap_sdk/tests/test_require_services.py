from __future__ import annotations

import shutil

import pytest
from rap_sdk.testing import REQUIRE_SERVICES, require_binary

MISSING = "rap-no-such-server-binary"


def test_a_present_binary_is_found() -> None:
    assert require_binary("sh") == shutil.which("sh")


def test_a_missing_binary_skips_outside_ci(monkeypatch: pytest.MonkeyPatch) -> None:
    monkeypatch.delenv(REQUIRE_SERVICES, raising=False)
    with pytest.raises(pytest.skip.Exception, match=f"{MISSING} is not installed"):
        require_binary(MISSING)


def test_a_missing_binary_fails_when_services_are_required(
    monkeypatch: pytest.MonkeyPatch,
) -> None:
    monkeypatch.setenv(REQUIRE_SERVICES, "1")
    with pytest.raises(pytest.fail.Exception, match="servers are required here"):
        require_binary(MISSING, hint="apt-get install it")
