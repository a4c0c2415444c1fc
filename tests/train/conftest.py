"""Fixtures of the training tests."""

from __future__ import annotations

import pytest


@pytest.fixture
def restore_render_backend():
    from mideepbasis.render import render_backend, set_render_backend

    before = render_backend()
    yield
    set_render_backend(before)
