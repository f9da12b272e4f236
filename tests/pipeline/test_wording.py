"""The words the panel, the reports and the CLI share (facelab_addon.pipeline.wording)."""

from types import SimpleNamespace

import pytest

from facelab_addon.pipeline import wording


@pytest.mark.parametrize("score, word", [(0.0, "reliable"), (0.13, "reliable"), (0.5, "reliable"),
                                         (0.51, "uncertain"), (1.0, "uncertain"), (1.01, "guessing"), (3.2, "guessing")])
def test_extrapolation_bands(score, word):
    assert wording.extrapolation_word(score) == word


def test_extrapolation_tooltip_gives_the_number_and_the_bands():
    tip = wording.extrapolation_tooltip(0.1349)
    assert tip.startswith("Extrapolation 0.13 on this frame")
    assert "reliable up to 0.5" in tip and "uncertain up to 1" in tip and "guessing beyond" in tip


@pytest.mark.parametrize("metres, text", [(0.0009358, "0.94 mm"), (0.0, "0.00 mm"), (0.00004, "0.04 mm"),
                                          (0.0123, "12 mm"), (0.00012, "0.12 mm")])
def test_mm(metres, text):
    assert wording.mm(metres) == text


def test_held_fixed_names_what_was_held():
    assert wording.held_fixed("vertex group 'FL_fixed'", "FL_fixed") == "held fixed: the vertex group 'FL_fixed'"
    parts = wording.held_fixed("separate mesh parts", "Hidden")
    assert "not joined to the face" in parts and "vertex group 'Hidden'" in parts


def test_model_sentence_and_headline():
    assert wording.model_sentence(1.0) == "predicting the lips' whole motion from the mouth"
    assert wording.model_sentence(0.0) == "adding the learnt correction to the captured lips"
    assert wording.model_sentence(0.22) == ("78 % adding the learnt correction to the captured lips, "
                                            "22 % predicting their whole motion from the mouth")
    head = wording.propagate_headline(48, 2.06, 9, 3, 0.22)
    assert head.startswith("Propagated to 48 frames in 2.1 s: 9 corrective shapes learnt from 3 corrected frames, 78 %")
    assert wording.propagate_headline(48, 1, 1, 1, 1.0).startswith("Propagated to 48 frames in 1.0 s: 1 corrective "
                                                                    "shape learnt from 1 corrected frame, predicting")


def test_forced_whole_reason_reads_model_summary():
    from facelab_addon.pipeline.propagate import model_summary

    auto = SimpleNamespace(model="auto", whole_weight=0.22)
    assert wording.forced_whole_reason(model_summary(auto)) == ""
    assert wording.forced_whole_reason(model_summary(SimpleNamespace(model="whole", whole_weight=1.0))) == ""
    reason = wording.forced_whole_reason(model_summary(auto, unknown=[3, 7]))
    assert reason.startswith("training frames 3, 7 sculpted in place")
    assert reason in wording.propagate_headline(10, 1, 2, 2, 1.0, reason)


def test_join_leaves_out_empty_parts():
    assert wording.join(["a", "", None, "b"]) == "a; b"
