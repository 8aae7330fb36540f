"""The stage graph is validated when built: cycles, unknown inputs, duplicates, truth rules."""

from __future__ import annotations

import pytest

from pipeline.dag import Dag
from pipeline.errors import ConfigError
from pipeline.stage import Stage, StageContext, StageParams


def _noop(ctx: StageContext) -> None:
    return None


def _stage(name: str, *inputs: str, **kwargs) -> Stage:
    return Stage(name=name, inputs=tuple(inputs), params=StageParams, run=_noop, **kwargs)


def _graph() -> Dag:
    return Dag.build([
        _stage("capture", extra_outputs=("truth",)),
        _stage("calibrate", "capture"),
        _stage("calibrate_eval", "calibrate", "capture.truth", evaluates="calibrate"),
        _stage("track", "capture", "calibrate"),
        _stage("matte", "capture"),
        _stage("train", "track", "matte"),
    ])


def test_topological_order_and_selection() -> None:
    dag = _graph()
    order = dag.order
    assert order.index("capture") < order.index("calibrate") < order.index("track") < order.index("train")
    assert dag.select(until="track") == ["capture", "calibrate", "track"]
    assert dag.select(from_="track") == ["track", "train"]
    assert dag.select(from_="calibrate", until="train") == ["calibrate", "track", "train"]
    assert dag.select(only=["matte", "capture"]) == ["capture", "matte"]
    assert set(dag.select()) == set(order)
    assert dag.evaluator_of("calibrate") == "calibrate_eval"
    with pytest.raises(ConfigError, match="--until nope: unknown stage"):
        dag.select(until="nope")
    with pytest.raises(ConfigError, match="does not depend on"):
        dag.select(from_="matte", until="calibrate")


def test_cycle_is_named() -> None:
    with pytest.raises(ConfigError, match=r"cycle: (a -> b -> c -> a|b -> c -> a -> b|c -> a -> b -> c)"):
        Dag.build([_stage("a", "c"), _stage("b", "a"), _stage("c", "b")])
    with pytest.raises(ConfigError, match="own output"):
        Dag.build([_stage("a", "a")])


def test_unknown_input_and_duplicate_names() -> None:
    with pytest.raises(ConfigError, match="stage 'b': unknown input 'nothere'"):
        Dag.build([_stage("a"), _stage("b", "nothere")])
    with pytest.raises(ConfigError, match="declared twice"):
        Dag.build([_stage("a"), _stage("a")])
    with pytest.raises(ConfigError, match="declares no extra output 'truth'"):
        Dag.build([_stage("a"), _stage("a_eval", "a.truth")])


def test_truth_only_feeds_evaluation_stages() -> None:
    with pytest.raises(ConfigError, match="'track' takes ground truth 'capture.truth' but is not an evaluation"):
        Dag.build([_stage("capture", extra_outputs=("truth",)), _stage("track", "capture.truth")])
    ok = Dag.build([_stage("capture", extra_outputs=("truth",)),
                    _stage("report", "capture.truth", reads_truth=True)])
    assert ok.upstream["report"] == ("capture",)


def test_unloaded_stage_may_be_named_but_text_and_dot_show_it() -> None:
    dag = Dag.build([_stage("a"), _stage("c", "b")], unloaded=["b"])
    assert dag.select(until="c") == ["b", "c"]
    assert "b  [unloadable: boom]" in dag.to_text({"b": "boom"})
    assert '"b" -> "c";' in dag.to_dot()
