"""``--frames``: parsed and checked against Blender's limits and the shot (the scene's frame range)."""

from __future__ import annotations

import re

from ._errors import EXIT_USAGE, CliError


#: Blender's frame limits (``MAXFRAME``): no scene frame lies outside them.
MAX_FRAME = 1048574
#: More frames than this in one ``--frames`` is refused (a typo such as 1-3000000, not a shot).
MAX_FRAME_COUNT = 100_000


def parse_frames(text: str | None, scene) -> list[int]:
    """``'A-B'`` / ``'N'`` / ``'A,B,C'`` -> sorted frames; None -> the scene's range.

    Ranges are checked arithmetically before any list is built: frames must be
    0..``MAX_FRAME`` (the scene range of Blender and FaceLab's settings start
    at 0), a range must not end before it starts, and at most
    ``MAX_FRAME_COUNT`` frames are taken. Every frame must lie in the scene's
    frame range, the shot: frames past it are refused, not clamped (every
    command alike), so a typo never keys hundreds of frames of a held pose.
    """
    if text is None or text == "":
        return list(range(scene.frame_start, scene.frame_end + 1))
    spans = []
    for part in text.split(","):
        part = part.strip()
        m = re.fullmatch(r"(-?\d+)\s*(?:-|\.\.|:)\s*(-?\d+)", part)
        if m:
            a, b = int(m.group(1)), int(m.group(2))
            if b < a:
                raise CliError(f"--frames {text!r}: the range {a}-{b} ends before it starts; write it as "
                               f"{b}-{a}.", EXIT_USAGE)
        elif re.fullmatch(r"-?\d+", part):
            a = b = int(part)
        else:
            raise CliError(f"--frames {text!r}: expected 'A-B', 'N' or a comma list such as '1-100,120'.", EXIT_USAGE)
        if a < 0:
            raise CliError(f"--frames {text!r}: frame {a} is negative; Blender's scene range (and FaceLab's) starts "
                           "at frame 0. Shift the animation to frame 0 or later (or re-export the cache starting "
                           "there).", EXIT_USAGE)
        if b > MAX_FRAME:
            raise CliError(f"--frames {text!r}: frame {b} is past Blender's last frame {MAX_FRAME:,}; give the "
                           "shot's frames.", EXIT_USAGE)
        spans.append((a, b))
    spans.sort()
    merged = []
    for a, b in spans:
        if merged and a <= merged[-1][1] + 1:
            merged[-1][1] = max(merged[-1][1], b)
        else:
            merged.append([a, b])
    count = sum(b - a + 1 for a, b in merged)
    if count > MAX_FRAME_COUNT:
        raise CliError(f"--frames {text!r}: {count:,} frames, more than the {MAX_FRAME_COUNT:,} one run takes; "
                       "check the range for a typo, or split the shot into several runs.", EXIT_USAGE)
    lo, hi = int(scene.frame_start), int(scene.frame_end)
    outside = [f for f in (merged[0][0], merged[-1][1]) if not lo <= f <= hi]
    if outside:
        raise CliError(f"--frames {text!r}: frame {outside[0]} is outside the shot, whose frame range is {lo}-{hi} "
                       "(the scene's Frame Start / End); give frames inside it, or set the scene's frame range to "
                       "the frames the capture covers and save the .blend first.", EXIT_USAGE)
    return [f for a, b in merged for f in range(a, b + 1)]


def contiguous(frames: list[int], what: str) -> tuple[int, int]:
    """(first, last) of a gap-free, non-empty frame list (the operators take a range)."""
    if not frames:
        raise CliError(f"{what}: no frames to work on; give --frames as 'A-B' (or set the scene's frame range).",
                       EXIT_USAGE)
    if frames != list(range(frames[0], frames[-1] + 1)):
        raise CliError(f"{what} works on one frame range; give --frames as 'A-B'.", EXIT_USAGE)
    return frames[0], frames[-1]
