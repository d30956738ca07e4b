"""A callback that raises is answered, logged once at error severity and counted."""

import logging
import types

from galvoscan_common.boundary import CallbackErrors, guard_service, guard_subscription


class _Logger:
    def __init__(self):
        self.lines = []

    def error(self, text):
        self.lines.append(text)


def _response():
    return types.SimpleNamespace(success=True, message='')


def test_service_failure_becomes_a_failed_response():
    errors, log = CallbackErrors(), _Logger()

    def callback(req, resp):
        if req == 'oom':
            raise MemoryError()
        if req == 'bad':
            raise ValueError('steps_pan: need at least 1 step, got 0')
        resp.message = 'ok'
        return resp

    srv = guard_service('scan/start', callback, log, errors)
    resp = srv('oom', _response())
    assert resp.success is False and resp.message == 'scan/start failed: MemoryError: MemoryError'
    resp = srv('bad', _response())
    assert resp.success is False and 'steps_pan: need at least 1 step' in resp.message
    assert 'ValueError' not in resp.message  # a ValueError is the caller's mistake, said plainly
    resp = srv('fine', _response())
    assert resp.success is True and resp.message == 'ok'
    assert errors.as_dict() == {'scan/start': 2} and errors.total == 2
    assert len(log.lines) == 2 and '(failure 2 of this service)' in log.lines[1]


def test_subscription_failure_is_skipped_and_counted():
    errors, seen = CallbackErrors(), []
    log = logging.getLogger('test_boundary')

    def callback(msg):
        if msg is None:
            raise TypeError('no message')
        seen.append(msg)

    sub = guard_subscription('stripe/centers', callback, log, errors)
    sub(None)
    sub(1)
    assert seen == [1] and errors.as_dict() == {'stripe/centers': 1}


def test_interrupts_are_not_swallowed():
    def callback(req, resp):
        raise KeyboardInterrupt

    srv = guard_service('x', callback, _Logger(), CallbackErrors())
    try:
        srv(None, _response())
    except KeyboardInterrupt:
        pass
    else:
        raise AssertionError('KeyboardInterrupt was swallowed')


def test_failures_show_in_the_diagnostics_status():
    from diagnostic_msgs.msg import DiagnosticStatus

    from galvoscan_common.diagnostics import status

    errors = CallbackErrors()
    counters = {'frames': 7, 'skipped': {'laser_off': 2, 'malformed_cdr': 0}}
    ok = status('n: work', counters, errors, '7 frames', warn=('skipped/malformed_cdr',))
    values = {kv.key: kv.value for kv in ok.values}
    assert ok.level == DiagnosticStatus.OK and ok.message == '7 frames'
    assert values == {'frames': '7', 'skipped/laser_off': '2', 'skipped/malformed_cdr': '0',
                      'callback_errors': '0'}
    counters['skipped']['malformed_cdr'] = 1
    assert status('n: work', counters, errors, warn=('skipped/malformed_cdr',)).level == \
        DiagnosticStatus.WARN

    timer = guard_subscription('poll', lambda: 1 / 0, _Logger(), errors)
    timer()
    timer()
    bad = status('n: work', {'frames': 7}, errors, '7 frames')
    values = {kv.key: kv.value for kv in bad.values}
    assert bad.level == DiagnosticStatus.WARN
    assert values['callback_errors'] == '2' and values['callback_errors/poll'] == '2'
    assert bad.message == '7 frames; 2 failed callbacks'
