"""A launch whose router cannot start leaves the caller as it found it: its signal handlers back."""

import signal

import pytest

from launcher import fleet

from .conftest import make_run


def test_a_failed_start_puts_the_callers_signal_handlers_back(monkeypatch, tmp_path):
    _, spec, _ = make_run()

    def no_router(*_args, **_kwargs):
        raise RuntimeError("router did not come up")

    monkeypatch.setattr(fleet, "_start_router", no_router)
    before = {name: signal.getsignal(getattr(signal, name)) for name in fleet.STOP_SIGNALS}
    with pytest.raises(RuntimeError, match="router did not come up"):
        fleet.launch_fleet(spec, workdir=tmp_path, crashes=[], restart_after=0.0, restart=True,
                           zenoh_port=None, progress=False)
    assert {name: signal.getsignal(getattr(signal, name)) for name in fleet.STOP_SIGNALS} == before
