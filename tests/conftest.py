"""What every test file shares: the hardware marker's skip, in one place.

``@pytest.mark.hardware(needs="the real gate", env=("VS2T_GATE_PORT",))`` runs only on the cell,
with ``VS2T_HARDWARE=1`` and the named variables set; anywhere else it is skipped with a reason
that says what to set. ``@pytest.mark.slow`` marks tests that take more than a few seconds (the UR
simulator rows, training runs, the wheel build): the default run keeps them (CI runs everything);
``pytest -m "not slow"`` is the quick loop while editing.
"""

from __future__ import annotations

import os

import pytest


def hardware_skip_reason(marker, environ=os.environ) -> str | None:
    """Why a ``hardware`` test cannot run here, or None when it can."""
    missing = [] if environ.get("VS2T_HARDWARE") == "1" else ["VS2T_HARDWARE=1"]
    missing += [name for name in marker.kwargs.get("env", ()) if not environ.get(name)]
    if not missing:
        return None
    return f"needs {marker.kwargs.get('needs', 'the real cell')}: set {' and '.join(missing)}"


def pytest_collection_modifyitems(config, items):
    for item in items:
        marker = item.get_closest_marker("hardware")
        if marker is not None:
            reason = hardware_skip_reason(marker)
            if reason:
                item.add_marker(pytest.mark.skip(reason=reason))
