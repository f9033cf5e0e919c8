"""``node.get_logger()`` takes rclpy's logging calls (throttle, once, skip-first, warn, fatal,
get_child, set_level, log(message, severity)) over a standard :mod:`logging` logger: code ported
from rclpy raised TypeError on ``throttle_duration_sec=``."""

from __future__ import annotations

import logging
import uuid

import pytest

from buffer_pubsub import Node
from buffer_pubsub import node_logger
from buffer_pubsub.node_logger import NodeLogger


@pytest.fixture
def logger(caplog):
    name = f"node_logger_test.n{uuid.uuid4().hex[:8]}"
    caplog.set_level(logging.DEBUG, logger=name)
    return NodeLogger(logging.getLogger(name))


def _messages(caplog) -> list[str]:
    return [record.getMessage() for record in caplog.records]


def test_a_throttled_call_site_logs_its_first_call_then_once_per_interval(logger, caplog,
                                                                          monkeypatch):
    now = [1000.0]
    monkeypatch.setattr(node_logger.time, "monotonic", lambda: now[0])
    logged = []
    for step in range(6):
        logged.append(logger.info("tick %d", step, throttle_duration_sec=1.0))
        now[0] += 0.4
    assert logged == [True, False, False, True, False, False]
    assert _messages(caplog) == ["tick 0", "tick 3"]


def test_once_and_skip_first_are_kept_per_call_site_in_rclpys_order(logger, caplog):
    for step in range(3):
        logger.warn(f"once {step}", once=True)
        logger.warn(f"other site {step}", once=True)
        logger.info(f"skip {step}", skip_first=True)
        logger.info(f"both {step}", skip_first=True, once=True)  # the second call only
    assert _messages(caplog) == ["once 0", "other site 0", "skip 1", "both 1", "skip 2"]


def test_a_disabled_level_logs_nothing_and_uses_up_no_filter(logger, caplog):
    logger.set_level(logging.WARNING)
    assert logger.info("hidden", once=True) is False
    logger.set_level(logging.DEBUG)
    for _ in range(2):
        logger.info("shown once", once=True)
    assert _messages(caplog) == ["shown once"]


def test_records_name_the_callers_line_and_rclpys_names_work(logger, caplog):
    assert logger.info("here", once=True) is True
    line = test_records_name_the_callers_line_and_rclpys_names_work.__code__.co_firstlineno + 1
    (record,) = caplog.records
    assert (record.filename, record.lineno) == ("test_node_logger.py", line)
    child = logger.get_child("camera")
    assert child.name == logger.name + ".camera"
    assert child.fatal("down") is True and caplog.records[-1].levelno == logging.CRITICAL
    assert logger.log("rclpy order", 40) is True and caplog.records[-1].levelno == logging.ERROR
    assert logger.log(logging.INFO, "python order %s", "ok") is True
    assert caplog.records[-1].getMessage() == "python order ok"
    try:
        raise KeyError("boom")
    except KeyError:
        logger.exception("failed")
    assert caplog.records[-1].exc_info[0] is KeyError
    assert logger.is_enabled_for(logging.DEBUG) and logger.get_effective_level() == logging.DEBUG


def test_bad_filter_arguments_are_typed_errors(logger):
    with pytest.raises(ValueError, match="RCUTILS_STEADY_TIME"):
        logger.info("x", throttle_duration_sec=1.0, throttle_time_source_type="RCUTILS_ROS_TIME")
    with pytest.raises(ValueError, match="throttle_duration_sec"):
        logger.info("x", throttle_duration_sec="soon")
    with pytest.raises(TypeError):
        logger.info("x", every_n=3)
    with pytest.raises(TypeError):
        logger.log("message", "not a level")
    with pytest.raises(ValueError):
        logger.get_child("")


def test_a_node_keeps_one_logger_named_as_rclpy_names_it(domain):
    with Node("talker", namespace="/robot1", domain_id=domain, fast_lane=False) as node:
        first = node.get_logger()
        assert first is node.get_logger()  # filters keep their state across calls
        assert isinstance(first, logging.LoggerAdapter) and first.name == "robot1.talker"
        assert first.logger is logging.getLogger("robot1.talker")


def test_throttle_is_judged_before_skip_first_as_in_rclpy(logger, caplog, monkeypatch):
    """rclpy: the first call passes the throttle (starting its interval) and is skipped; the
    next one inside the interval is throttled; the one after it logs."""
    now = [50.0]
    monkeypatch.setattr(node_logger.time, "monotonic", lambda: now[0])
    results = []
    for step in range(3):
        results.append(logger.info(f"call {step}", throttle_duration_sec=1.0, skip_first=True))
        now[0] += 0.6
    assert results == [False, False, True]
    assert _messages(caplog) == ["call 2"]


def test_a_call_site_whose_filters_change_is_refused_as_in_rclpy(logger):
    for duration in (1.0, 2.0):
        try:
            logger.info("computed interval", throttle_duration_sec=duration)
        except ValueError as error:
            assert "cannot change" in str(error)
            break
    else:
        pytest.fail("a changed throttle_duration_sec was taken as a new call site")


def test_the_wrapped_loggers_attributes_and_methods_are_the_node_loggers(logger, caplog):
    logger.propagate = False  # as on a logging.Logger: caplog's handler no longer sees it
    try:
        assert logging.getLogger(logger.name).propagate is False
        records: list[logging.LogRecord] = []
        handler = logging.Handler()
        handler.emit = records.append  # type: ignore[method-assign]
        logger.addHandler(handler)
        assert logger.handlers == [handler] and logger.getChild("x").name == logger.name + ".x"
        logger.info("to my handler")
        assert [r.getMessage() for r in records] == ["to my handler"] and not caplog.records
    finally:
        logger.propagate = True
        logger.logger.handlers.clear()


def test_a_node_named_root_has_a_logger_of_its_own_not_the_root_logger(domain):
    with Node("root", domain_id=domain, fast_lane=False) as node:
        logger = node.get_logger()
        assert logger.logger is not logging.getLogger() and logger.name == "root"
        assert logger.logger.parent is logging.getLogger()  # its records still propagate
