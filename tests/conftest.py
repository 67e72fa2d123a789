"""Shared fixtures. Tests render with the best JIT variant this machine has (llvm_ad_rgb on CI)."""
import pytest

from admc.pipeline.variants import use_variant


@pytest.fixture(scope="session")
def variant() -> str:
    """Activate the render variant once per test session (like Mitsuba's own variant fixtures)."""
    return use_variant("auto")
