"""Coarse-to-fine SSD tracking, and the checks that reject a match that cannot be trusted.

A single-level search of Eq. (1) finds a displacement only within SEARCH_SIZE // 2 of the
prediction, and widening the search gives repetitive texture more room for a false minimum. As
in Bouguet's pyramidal Lucas-Kanade, the frames are reduced into a pyramid (level k: the frame
filtered by the binomial [1 4 6 4 1]^2 / 256 and halved k times, as ``cv2.pyrDown`` does; its
pixel (x, y) lies at (2^k x, 2^k y) of the frame) and each feature is tracked coarse to fine
(:func:`track_pyramid`):

0. **follow** (``follow``): a feature tracked into frame t, or chosen in it and predicted by
   the frame's motion or, in a track's first frame, by no motion (``held``; the tracker holds
   every feature), is first refined by Gauss-Newton from its prediction alone, at the frame's
   level and, where that does not converge within a pixel, coarse to fine (:func:`_follow`);
   it is taken when its way back returns to within ``FOLLOW_FB`` ``max_fb_error`` of its
   start, or without the way back when it lands within FOLLOW_NEAR of a prediction made
   from measured motion (not a track's first pair's), unless most held features fail to
   follow (the frame broke the prediction). From a prediction of no motion, a feature too
   near the frame's edge for a coarser level runs once more at its own level from where
   Gauss-Newton strayed past its pixel (FOLLOW_STRAY_PX). Steps 1 to 4 then run for the others only;
   steps 5 and 6 for all. With steady motion the prediction is good to a few hundredths of
   a pixel, and a search finds what Gauss-Newton from the prediction finds, at several
   times the cost;
1. **start**: Eq. (1) is searched with the paper's windows at the coarsest level whose pixels
   hold the feature's template, around its prediction: SEARCH_SIZE // 2 px of that level reach
   2^k times as far in the frame, and the correlation window sees 2^k times as much of the
   scene. The start fails when the minimum lies on an edge of the search that the image cut
   short, on the border of the search window (the true minimum may lie outside it), or when a
   displacement outside the minimum's 3x3 neighbourhood is nearly as good: S below
   ``uniqueness`` times the minimum plus what the camera's noise alone adds to S at a perfect
   match (2 sigma^2 sum W, sigma shrinking with each reduction; repetitive texture). A failed
   start starts again one level finer; at the frame's own level the feature is not found;
2. **refine**: at each finer level the displacement, doubled, is refined: with sub-pixel
   refinement by Gauss-Newton on Eq. (1) (:func:`.ssd._refine`: Bouguet's scheme with an SSD
   search at its coarse end), else, or where Gauss-Newton cannot run, by a descent on the
   integer displacements (:func:`_descend`, at most DESCENT_STEPS moves, else the feature is
   not found);
3. **guided retry**: a feature that found no trustworthy minimum around its own prediction is
   searched again around the frame's dominant motion (the median displacement of the features
   found), with the same tests; so is one whose window left the frame around a prediction
   that departs from that motion by more than DOMINANT_PX. A frame in which fewer than BROKEN
   (half) of the features were found after steps 0 to 6 broke their predictions (a first pair
   taken in motion, a bump), and so did one where most features tracked before did not
   follow and the matches found moved more than the search's reach otherwise than predicted
   (:func:`_broke`: the step back after a jump, where the few found first misguided the
   others): every feature is tracked again, steps 1 to 6, around the frame-wide shift that
   phase correlation finds (:func:`frame_shift`, in :func:`track_pyramid`), and that run is
   kept where it found more by more than RETRY_MARGIN of the features. Crops of the shared
   frames moved 42 to 52 px between the first two (beyond the coarsest search's 4 x 7 px):
   60 % or more found, against almost none;
4. **forward-backward check** (Kalal, Mikolajczyk and Matas 2010): every match is tracked
   back from frame t+1 to frame t the same way, its prediction mirrored, held to the same
   tests; it is rejected when it does not return to within ``max_fb_error`` px of where it
   started. With sub-pixel refinement the way back skips the levels in between: its coarse
   minimum need only land within a pixel of that level of the start, and Gauss-Newton at the
   frame's level then runs from the start itself (:func:`_back_check`; a refinement that
   cannot run there takes the full way back). The way back needs its coarse search and its
   tests: a refinement from the start alone returns there even from a lookalike 23 px away
   (tried: the occlusion tests failed),
   and without the uniqueness test a start on repetitive texture is taken at the coarse level
   rather than searched again a level finer, which rejected up to 6 % more good matches
   (tried: a known shift of a real image kept 79 of 100 features, against 84);
5. **consensus**: a match whose displacement departs from the median of its nearest
   neighbours' by more than ``consensus`` px (and more than their own spread) is rejected: a
   lookalike taken for the feature, which the other tests miss when the two match each other
   both ways (a feature occluded next to a repetition of itself; :func:`_consensus`);
5b. **the dominant motion as a second minimum** (with the uniqueness test): a searched match
   (not followed: following cannot jump a period) whose displacement departs from the frame's
   dominant motion (the median of the matches') by more than DOMINANT_PX is rejected as
   ambiguous when that motion's displacement (or a neighbour of it outside the match's own 3x3)
   fits its template about as well, by the uniqueness test's bound
   (:func:`_dominant_alternative`). A coarse level can alias a repetitive texture: crops of
   RubberWhale moved (10, 3) px between a first pair put 7 of 84 features on its knit one
   period (~11 px) off, all agreeing with each other and with themselves both ways; now none,
   on the five sources. The scoreboard's rendered sequences are unchanged; its pairs with
   motion boundaries: Grove2 94 pairs at 0.105 px -> 93 at 0.102, Urban2 82 at 0.086 -> 77 at
   0.085 (the same 4 off by more than 2 px). Tested on every match it cost the bench's frames
   11 to 14 us (4 to 5 %: a quarter of them depart from the median by 2 px, and their
   alternatives are summed); on the searched ones only, +4 us on frames whose features were
   held (old and new side by side in one process, 60 interleaved rounds, best of them), within
   the rounds' spread. Where the scene has depth, the feature's motion lies away from the
   frame's and those whole pixels miss it: the match is also followed by Gauss-Newton from the
   dominant motion, and a minimum found more than DOMINANT_FOLLOW_PX away is compared with
   the match's at both sub-pixel positions. On Middlebury's Urban3 (not in the shared data),
   4 of 82 features whose window holds one motion took a facade's period (5 px) beside their
   own; now 1 of 79, and none of 428 with up to 500 features (3 of 430 before). The
   scoreboard is unchanged but RubberWhale's approach (0.46 -> 0.15 % off by more than 2 px).
   Nor is the frame's motion the feature's where the camera shakes or zooms: a searched match
   that departs from its prediction by more than PERIOD_DEPART_PX is also tested a period of its
   own texture either way (the template's best match in frame t itself within PERIOD_REACH
   px, :func:`_period_alternative`): RubberWhale's knit in the scoreboard's shake and approach,
   2 and 1 pairs off -> none, the shake's survival 0.59 -> 0.64 (LK's). Where the correlation
   window scores such a rival about as well as the match, the wide window decides
   (WIDE_ARBITER): on Urban2's facades it keeps right matches (its shake 0.80 -> 0.83 with
   the period test). Held out (Urban3, Sintel; 100 and 500 features): 1 to 8 fewer pairs off
   by more than 2 px on 10 of the 42 runs, none more;
5c. **rescue** (``consensus`` and ``max_fb_error`` > 0, sub-pixel): a match rejected by a
   test of its search (steps 1 to 5b: border, ambiguous, runaway, the way back, the
   consensus) whose NEIGHBOURS nearest matches move as one surface (a similarity fits their
   displacements to within RESCUE_FIT_PX rms, else an affine map those of its
   RESCUE_AFFINE_NEAR nearest) is followed by Gauss-Newton from the displacement that fit
   gives at its point, as Lucas-Kanade would be from a good
   guess, and kept where it lands within RESCUE_NEAR_PX of it and its way back returns to
   within FOLLOW_FB ``max_fb_error`` of its start, as a followed match's must
   (:func:`_rescue`). A search fails where its prediction was far off and its coarse level
   aliased a repetitive texture: a camera shaking by up to 6 px a frame at random (the
   prediction 12 px off at the median) lost 64 of RubberWhale's features to the way back,
   the consensus and ambiguity in 30 frames, where Lucas-Kanade from the neighbours' motion
   found 98 % of them to within 0.5 px. Where the neighbours are not one surface (a motion
   boundary) their motion is not the feature's: there it keeps its status. A rolling shutter
   that shakes shears a neighbourhood's motion (each row exposed at its own jolt), which no
   similarity fits: with the affine fit RubberWhale's shake read out over 0.9 of the frame
   interval kept 0.47 of its features, not 0.27 (LK 0.72), and Urban2's 0.69, not 0.51
   (LK 0.87);
6. **wide sub-pixel window**: Gauss-Newton again over a wider window (21 px by default), whose
   estimate is taken where the wide window's neighbourhood moves as the correlation window's
   centre does (:func:`_widen`): at the correlation window's estimate, each side of its ring
   fits frame t+1 about as well as its centre (a mean squared residual at most STRADDLE
   times the centre's, plus noise's; :func:`_ring_fit`), or, failing that, at the wide
   estimate every side fits at most EVEN times as badly as the centre. A surface at another
   depth, or a motion boundary, in the wide window leaves a side that does not fit the
   centre's motion; noise, and motion blur that changes from frame to frame (it moves the
   small window's estimate), leave the residual all round. Until 2026-12-07 the wide estimate
   was taken where it agreed with the correlation window's to within 0.1 px (more with
   noise), or where the ring fitted the wide estimate within STRADDLE times the centre: on
   real scenes with depth that took the neighbourhood's average (with up to 500 features
   Grove2's and Urban2's median 0.077 and 0.072 px, now 0.063 and 0.067; held out, with 100,
   Grove3 0.249 -> 0.196, Urban3 0.062 -> 0.048). On the rendered sequences blurred by a
   shutter open half and all of the frame interval (:func:`.rendered.motion_blurred`) ours is
   0.79 to 0.91 and 0.96 to 1.08 times LK's median error (0.93 to 1.05 before; with the side
   test at the small window's estimate alone up to 1.13; without the wide window 1.26 to 1.63
   and 1.79 to 2.27). Its cost: the ring fit (~0.4 us) for every match the wide window
   refines (before, for the quarter that disagreed by more than the bound), and a second
   where a side does not fit: a held frame of the bench's +20 to +34 us (old and new in
   turn, three processes each, best of 150 rounds: 371 to 411 -> 404 to 439 us with the
   pre-processing);
7. **the window's centroid** (with sub-pixel refinement; AFFINE_FIT_PX, 0: off): a
   translation estimated over a window whose neighbourhood also scales or turns (an approach,
   a roll) is the motion at the window's texture-weighted centroids (the turn's differs from
   the scale's), not at its centre. Each estimate is moved to its feature's point by the scale
   and rotation of a similarity fitted to its nearest matches' displacements, where they fit
   one, else by their affine map where they fit that (a plane in perspective)
   (:func:`_affine_correction`). On
   the scoreboard's approaches (10 % a frame) the median error fell from 0.16 to 0.24 px to
   0.05 to 0.07 (LK 0.27 to 0.33); elsewhere it moved by a few thousandths. Cost: ~25 us a
   frame on the bench's frames (step 7 on and off in one process, best of 200 rounds); ~7 us
   less since it takes its matches' neighbours from the consensus's, searching again only
   next to a match rejected since (:func:`_reused_neighbourhoods`: the same lists; the
   tracker 332.5 -> 325.3 us a frame, old and new side by side, best of 200 rounds, the same
   outputs).

With one level, no test and no retry this is the paper's single-level search, exactly
:func:`.ssd.track_ssd`.

A pyramid is one flat uint8 buffer with a table of its levels' offsets and shapes
(:class:`Pyramid`), which the kernels view level by level without copying; a numba typed List
of arrays was slow to pass to a kernel and slower to compile.

Where the time goes (83 features a frame, 256x256, the steps added one by one, in units of the
single-level (15, 9) search timed in the same rounds, under load): the coarse-to-fine search
alone 2.2, sub-pixel refinement +0.1, the uniqueness test +0.5, the guided retry +0.2, the
forward-backward check +2.6 (a second coarse-to-fine search, with its tests), the consensus +0.7
and the wide window +0.9: 7.2 in all (main before the flat buffer: 7.25). Five Gauss-Newton
refinements a feature (two levels each way and the wide window), ~0.6 us each for the
correlation window and ~1 us for the wide one, are about 40 % of the total.

Since then (issue 12's speed target, measured old against new compiled side by side in one
process, interleaved, best of 40 rounds, bench data): the way back without its middle-level
refinement (step 4) 740.7 -> 677.1 us, the uniqueness test visiting only the displacements that
pass their bound and the wrapper's cached sum type 677.1 -> 650.9 us, against the single-level
search's 110.2 us of the same rounds: 6.72x -> 5.90x; the same statuses. Counted on the same
data: a third of the features (31 %) cannot start at the coarsest level (their template leaves
it: within ~16 px of the frame's edge) and start a level finer, whose search and uniqueness
test cost more per feature (smoother images, weaker bounds); each way holds ~1.5 searches a
feature. Tried and dropped: two levels (Urban2's pair loses to LK, 0.094 against 0.087 px); a
wide window of 17 px (every median still at most LK's, but RubberWhale rendered at 0.040
against 0.041: too thin a margin for ~0.4x); the patch copies of Gauss-Newton by flat index or
in blocks of 8, and a brute-force nearest-neighbour search for the consensus (no measurable
gain side by side).

Then step 0 (``follow``, issue 12, quiet machine, ``vistrack bench tracker``): 632.2 -> 311.6
us a frame (8.03x -> 3.83x the single-level search); 242.2 us (2.98x) on the frames whose
features were all tracked before. What a followed feature costs: two 9x9 Gauss-Newton
refinements (there and back, ~0.4 us each) and the wide window's (~0.9 us); the wide window
is now the costliest step (82 us a frame), then the few features that are searched (edge
features, whose window Gauss-Newton cannot sample: ~15 us each, most of it fixed costs).

Where a frame's time goes now (each kernel timed alone on the bench's inputs, interleaved, best
of 100 rounds, a loaded machine: LK level 0 ~110 to 170 us in the same runs). A frame whose
features were tracked before (~82 features): 262 us, of which following them (two 9 x 9
Gauss-Newton refinements a feature, there and back) 106, the wide window 85, the 1 to 6
features searched (both ways, each ~4 searches and their fixed costs) 45, the consensus 22. The
bench's first frame pair (every feature new, so searched): 1040 us, of which the search 345 and
the way back 354 (per feature ~0.9 us at the coarsest level, ~1.9 us a level finer for the 45 %
that fail there or whose template does not fit it), the wide window 127. Inside a 9 x 9
refinement (~0.55 us): the two patch copies ~0.13, the gradient sums ~0.11, one set of corner
sums ~0.05, the iterations the rest; 21 x 21: 0.21, 0.35, 0.10 of ~1.0. Its int32 sums run at
the one-vector-multiply-a-cycle rate: 16-bit data would halve them only with pmaddwd, which LLVM
does not emit for these loops (tried: int16 patches and gradients made the 21 x 21 gradient
loop 1.85x slower), and patch rows copied in constant 16-pixel chunks were slower too (1.15x at
9 x 9, 1.3x at 21 x 21). Checked again on this machine's AVX-512 core: even the plainest
16-bit loop, ``h11 += int32(ddx) * int32(ddx)`` and two more sums over int16 differences, came
out as 32-bit multiplies (vpmulld), no vpmaddwd, and the 9-sum gradient loop of the 21 x 21
window in int16 ran as fast as in int32 (1.07 against 1.08 us a call, call included).

Then (issue 12 and 15's speed targets, 2026-12-04): perf on the bench's held frames put 37 % of
the default tracker's time in numba's runtime, NRT_incref and NRT_decref: every view a kernel
made (the template's slices in each Gauss-Newton refinement, the tuple of its scratch arrays,
a pyramid level per feature followed, a row of neighbours per fit) took an atomic increment
and decrement of its buffer's count, which LLVM cannot remove across the kernels' branches.
The kernels that neither allocate nor keep an array are now compiled without the runtime
(:data:`.ssd.NO_NRT`), the per-feature loop of step 0 moved into one (:func:`_follow_each`),
its levels' views made there (:func:`_refine_at`): 224 -> 143 us a held frame pair, the
(15, 9) search 41.5 -> 35.9 us, the same outputs bit for bit (every position, id and estimate
of the bench's frames, the default, paper's and exhaustive trackers and five rendered
sequences, compared; the scoreboard's table unchanged). What is left of the runtime: ~3 %.

Then (the same day): perf's samples mapped to the JIT code's instructions (objdump of each
function's bytes) found, in the refinement, the patch rows copied through LLVM's run-time
overlap check and a scalar remainder (:func:`.ssd._patch`, 15 % of a held frame), the second
differences computed in 64 bits (numba types int32 - int32 as int64), and every refinement
summing the window's centroid in int64 where only the wide window's is read. Rows now go as
whole vectors (:func:`.ssd._patch`), the differences in int32, the centroid where asked
(:data:`.ssd.CENTROID`): a held frame pair 143 -> 121 us, the same outputs bit for bit. Tried
and not kept: multiplying by 1/det and 1/6 in the iterations, and a looser stopping step
(3e-2 px): no measurable change, the iterations are not where the time goes.

Then (2026-12-05): LLVM does emit the 16-bit multiply-add, where one factor of each product is
known to fit 15 bits unsigned (zero-extended from uint8) and the other 16 bits signed: a
32-bit product then needs no vpmulld, and is one vpmaddwd, or with the accumulation one
vpdpwssd on a core with AVX-512 VNNI. The refinement's patches are now the frames' bytes and its
weighted gradients int16 (where its sums are int32: weights up to 128), and every sum is
a gradient times a pixel: ``Sum gx (right - left)`` is summed as ``Sum gx right - Sum gx
left``, the second and third differences likewise (10 sums and 8 where there were 9 and 4,
each half the instructions). The wide window's centroid is summed in int32 where no sum can
overflow it (its terms bounded by the window's size), not int64: 310 -> 166 ns a call. A 21 x
21 refinement with its centroid 1142 -> 909 ns, a 9 x 9 one 378 -> 337 ns (the iterations'
scalar arithmetic, a chain of dependent divisions, is now most of it); a held frame pair of
the default tracker 263 to 274 -> 239 to 242 us (best of 40 rounds, old and new run in turn
twice), and with numba targeting an AVX2 core (haswell: vpmaddwd, no VNNI) 259 to 269 -> 235
to 239 us. The same outputs bit for bit (374,310 values: every position, id and estimate of
the default, paper's and exhaustive trackers, the default with Gaussian weights, with a 31 px
window and a 41 px wide one (the int64 sums), and a 5 px Gaussian one, on five rendered
sequences and the built-in one).

Then, the same day: LLVM's vectoriser put one such product in each 32-bit lane of its
multiply-add, half its work, in the loops of 8 or 10 sums (a loop of one sum got the pairs).
:func:`.ssd._pixel_dots` writes the pairs in plain LLVM vector code (extend, multiply, add the
even lanes to the odd), which the x86 backend makes into vpmaddwd or vpdpwssd on any core:
eight sums of 640 pixels 147 -> 24 ns. Every sum of the refinement goes through it, the
centroid's too where they fit int32 (the gradients times each pixel's i and j, in 16 bits).
A 21 x 21 refinement with its centroid 909 -> 499 ns, a 9 x 9 one 337 -> 255 ns; a held frame
pair ~240 -> ~210 us; the same outputs bit for bit. What a held frame pair's time is now (perf,
by function): the refinement ~37 % (the patches' copies ~8 %, most of the rest the
iterations' scalar arithmetic), the neighbour search ~9 %, the wide window's ring fit ~5 %,
the similarity fits ~4 %, the few features searched coarse to fine (2 to 7 a frame, not
followed) ~15 %. Tried and not kept: the patches' rows copied 32 bytes at a time, not 16
(no change, within the rounds' spread).

Then (issue 12, 2026-12-07; old and new compiled side by side in one process, interleaved, best
of the rounds, the bench's frames): three kernels of steps 6 and 7. The ring fit
(:func:`_ring_fit`, a quarter of the features) reads the frames from the wide refinement's
patches, its residuals in 16 bits over the patches' lanes, a row's pad lanes masked, not 21
rows of views: 543 -> 411 ns a call. The correlation window's centroid, for the matches whose
wide estimate was not taken (~15 a frame), sums in int32 over a patch's lanes where no sum can
outgrow it (:func:`_centroid_fast`), vectorised, not in int64 a pixel at a time: 446 -> 197 ns.
The similarity fit loops over NEIGHBOURS, a constant (:func:`_similarity`): 77 -> 68 ns. A held
frame pair 277.4 -> 268.0 us, the first pair 343.7 -> 328.2 (LK 1214.9: 0.228x -> 0.221x; 150
rounds); the same outputs bit for bit (the bench's pairs, and 247,071 values: every id,
position and estimate of the default, paper's and Gaussian-weight trackers on the five rendered
sequences, RubberWhale's and Grove2's approach, shake and blur, and the built-in sequence).

Then (the same day): the features searched on a held frame (2 to 7 of ~95: the way back of
their follow failed) cost ~18 us each (the held frames 269.9 us, 210.6 with those features
left out). Part of it was fixed: :func:`_match` and :func:`_back_check` made every feature's
anchor and centre at each level (four divisions a feature), though a few were searched;
now the active ones' only (the others' are never read): a call with none active 3.03 ->
1.69 us, with one 8.89 -> 7.53; and step 5b no longer takes the frame's median where no
searched match is left to test. Still ~5 us a feature and level searched (one at level 0
alone ~6 us, three ~15: the row sums of its reach, the bounds, the search, the uniqueness
test), the exhaustive search no cheaper for one (6 against 6.5 us, the same results).

Measured the same day and not changed. The wide window's Gauss-Newton from the correlation
window's estimate (median 0.028 px apart, a quarter more than 0.1 px): 632 ns a feature, from
its own converged estimate 542: its 2 to 3 iterations ~90 ns, the rest its sums (the third
differences' ~40 ns, the centroid's ~130); summing its centre from the 9 x 9 refinement's
sums would save at most 81/441 of 18 of its 42 sums, the two windows' patches in layouts
of their own. The way back of a followed feature runs for ~20 % of them (FOLLOW_NEAR), a 9
x 9 refinement each, ~4 us a frame at most. A frame's kernels' allocations and scratch: the
wide window's scratch ~1.1 us, the correlation window's ~0.5, a call of the tracker with no
feature 6.3 us (2.2 of them the kernel's call, its 36 arguments; the rest plan.track's checks
and arrays). Tried and dropped: the ring fit's sums in float64 (exact: integers below 2^53),
3x slower (no fastmath: a float reduction is not reordered, so not vectorised), and its
residuals in int32 rather than 16 bits (no change).

Where a held frame pair's time goes now (the steps turned off one by one, in one process,
interleaved, best of 60 rounds, a loaded machine: 267.0 us in all): the 2 to 7
features searched 63 us (their own inputs left out), the wide window 88 (its refinement ~630
ns a feature alone, the ring fit ~410 for a quarter of them), step 7 31 (two similarity fits
a match, ~68 ns each; two affine fits, ~110 ns, for each of the ~45 matches no similarity
fits; ~15 correlation-window centroids), the consensus 22 (its neighbour search ~130 ns a
match alone), following ~88 features 54 (a 9 x 9 refinement, ~255 ns alone, S at the match,
a fifth of them their way back), plan.track's call 7.

Later that day step 6 tested the ring at the correlation window's estimate, so the ring fit ran
for every match the wide window refined (1 to 1.3 calls each), not a quarter of them: the wide
window's step took 111 to 117 us on the bench's frames (92 features), 63 to 80 without its
tests. The ring fit's sums then went the way of the refinement's (:func:`.ssd._masked_squares`):
in plain LLVM vector code, 32 residuals a vector, each masked per sum and squared in the pairs
of a 16-bit multiply-add, two vectors' pairs added in 32 bits before they are widened to 64,
where numba's loop ran 8 lanes a step and widened each square to 64 bits: 353 to 360 -> 138
to 153 ns a call, the wide window's step 111 to 117 -> 91 us; the same outputs bit for bit
(every position, id and estimate on the shared and held-out pairs, 100 and 500 features).
"""

from __future__ import annotations

import functools
from dataclasses import dataclass
from typing import TypedDict

import cv2
import numba as nb
import numpy as np

from ..params import SEARCH_KINDS
from .motion import _median_small
from .ssd import (
    AMBIGUOUS,
    BIG,
    BORDER,
    CENTROID,
    CUT,
    DISAGREES,
    DOT_LANES,
    FB,
    LANES,
    LEFT,
    MAX_COORD,
    NO_BUDGET,
    NO_NRT,
    NO_THIRD,
    OK,
    OVER,
    RING_MASKS,
    RUNAWAY,
    THIRD,
    _masked_squares,
    _parabola,
    _patch,
    _refine_scratch,
    _refine_with,
    _search_level,
    _ssd_at,
    _weights_info,
    _within,
    refine_acc,
)

#: most moves of a refinement descent at one level (the doubled match of the level above is
#: within about a pixel of the minimum when that match was right)
DESCENT_STEPS = 3
#: fewest features found for a frame's dominant motion to guide a retry
MIN_GUIDES = 3
#: the searches of Eq. (1) one frame may make, all levels and steps together, in window pixels
#: x displacements (the default tracker's ~100 features spend about 10^7): a feature whose
#: search would exceed what is left is not searched (OVER, lost: re-detection refills it).
#: At the parameters' limits (2000 features, search 128, correlation 64) a frame of searches
#: otherwise took up to 45 s, which a watchdog takes for a hang; this bounds one at ~1 s where
#: the pruned search prunes. Where it cannot (periodic texture: a frame of stripes, search 128,
#: a 38 px Gaussian window, 500 features) a unit costs ~4 times an exhaustive one: 2.3 s of
#: searches, 2.8 to 3.2 s for the frame (a fuzzer's worst case, 2026-12-06). The tracker's
#: calls for one frame (its zoom retry) draw on one budget.
FRAME_WORK = 10**10
#: Pixels the way back (step 4) searches beyond the way there's SEARCH_SIZE // 2 where its
#: minimum fell on that border: each way's window is centred on a whole pixel, so a right
#: match's minimum one way within the reach lies up to a pixel further the other way (on a
#: fast first pair, three right matches 33 px away were rejected for it).
BACK_MARGIN = 1
#: a frame in which fewer than this share of its features were found broke their
#: predictions (a jerk, a first frame pair taken in motion): with ``guided_retry`` it is
#: tracked again around the frame-wide shift (:func:`frame_shift`)
BROKEN = 0.5
#: ... and only where more than this share of the features was not found: the run again keeps
#: the second only where it found more (RETRY_MARGIN), so where the first lost fewer it can
#: win no more than that (the step back after the built-in replay's jump: 70 of 71 found, and
#: a second run of every feature, ~1.1 ms, for the 71st; re-detection refills a feature lost)
RETRY_GAIN = 0.05
#: the second run is kept where it found more than the first by more than this share of the
#: features: a few more are within the two runs' noise, and a run from another start brings
#: its own errors. On Urban2's pair (500 features) a retry around the foreground's shift
#: found 442 against 425, 3 more of them on motion boundaries taking the foreground's motion,
#: 2 to 10 px off
RETRY_MARGIN = 0.05
#: the side, px, of the coarsest level :func:`frame_shift` correlates: enough pixels for a
#: clear peak (at 256 x 256 with 3 levels, 64 x 64, ~40 us)
SHIFT_SIDE = 32
#: ... and at most this on its shorter side: a larger level is halved (INTER_AREA) until it is
#: not. ``cv2.phaseCorrelate`` took 1034 us on 1280 x 720's coarsest level, 320 x 180, and 136
#: us on 160 x 90 (one core); the retry's searches, which reach 2^k SEARCH_SIZE // 2 px from
#: it, refine what it finds
SHIFT_MAX_SIDE = 128
#: a match departing from the frame's dominant motion by more than this, px, has that motion
#: tested as a second minimum (step 5b, :func:`_dominant_alternative`)
DOMINANT_PX = 2.0
#: ... and is followed by Gauss-Newton from that motion: where it converges more than this
#: many px from the match, another minimum, compared with the match's at their sub-pixel
#: positions (inf: not tried). Where the scene has depth, the frame's dominant motion is not
#: the feature's, and the whole-pixel displacements around it miss the right period of a
#: repetitive texture: on Urban3's facade (Middlebury, not among the shared data: a period
#: of 5 px, the true motion 1.6 px from the frame's) 4 features took the period beside it
DOMINANT_FOLLOW_PX = 1.5
#: step 5b also looks for a searched match's texture's period: the template's best match in
#: frame t itself within this many px (outside its own 3x3), and tests the match a period
#: either way (0: not looked for). The coarse levels alias periods up to about 4 of their
#: pixels; RubberWhale's knit repeats every ~11 px
PERIOD_REACH = 12
#: ... where that self-match's S is at most this many times the noise's allowance (a
#: texture that repeats; beyond, no period to fear) ...
PERIOD_SELF = 30.0
#: ... for a match that departs from its prediction by more than this, px (one that lands
#: where it was predicted had no period to jump; and the self-match cost ~3 us a feature
#: on the pipeline's built-in frames, ~1 us since it is bounded, :func:`_self_match`)
PERIOD_DEPART_PX = 2.0
#: where step 5b's Gauss-Newton finds another minimum about as good by the correlation
#: window, the wide window (``refine_size``) decides: the match stands where the other
#: scores clearly worse there (by the uniqueness test's bound), as Lucas-Kanade's 21 x 21
#: window tells a facade's 5 px period apart; else it is AMBIGUOUS (False: always)
WIDE_ARBITER = True
#: how many of a match's nearest neighbours its displacement is compared with (step 5)
NEIGHBOURS = 6
#: step 7 corrects a match for its neighbourhood's scale and rotation where its NEIGHBOURS
#: nearest matches' displacements fit a similarity to within this, px rms (several times a
#: match's own error): one surface, moving as one (:func:`_affine_correction`)
AFFINE_FIT_PX = 0.2
#: step 5c follows a rejected match from its NEIGHBOURS nearest matches' motion where their
#: displacements fit a similarity to within this, px rms: one surface moving as one, as step 7
#: asks (0: off). Followed from their median where no similarity fits them within 0.5 px,
#: the pairs' motion boundaries paid: Urban2's features there took their neighbours' motion, 3
#: of 76 pairs off by more than 2 px -> 6 of 81 (with up to 500 features, 12 of 399 -> 19 of
#: 442); only where one fits within 0.5 px, 3 of 78 and 18 of 437; within 0.2, 3 of 78 and 17
#: of 436 with the consensus's 2 px as RESCUE_NEAR_PX, and 3 of 77 and 12 of 411 with 0.5
#: (:func:`_rescue`)
RESCUE_FIT_PX = AFFINE_FIT_PX
#: ... and takes it where it lands within this of their motion, px (or 3 times their fit's
#: rms, where more): a feature next to an occluding patch, taken with the consensus's 2 px,
#: was followed to 1.2 px off
RESCUE_NEAR_PX = 0.5
#: where its NEIGHBOURS nearest fit no similarity, step 5c fits an affine map to this many
#: nearest matches (0: off): a neighbourhood that shears (a rolling shutter that shakes, each
#: row exposed at its own moment) or a plane in perspective. Ten points leave the fit's six
#: parameters 14 residuals to judge it by; over six, nearly every neighbourhood fitted
RESCUE_AFFINE_NEAR = 10
#: where the neighbourhood is no similarity, step 7 fits an affine map (a plane in
#: perspective scales along x and y apart) and corrects by it where that fits instead
AFFINE_GENERAL = True
#: ... to within this share of AFFINE_FIT_PX: its two more parameters absorb more of the noise
AFFINE_GENERAL_FIT = 0.5
#: nor where the fitted scale and rotation, |a + b i|, exceed this: a scale step beyond 0.8 ..
#: 1.25 (the tracker's ZOOM_RANGE) is a frame's error, not an approach
AFFINE_MAX = 0.25
#: and only where that correction can reach this, px (the window's half-width times the
#: first fit's scale and rotation): below it the window's centroid is not worth computing
AFFINE_RELEVANT_PX = 0.02
#: the share of ``max_fb_error`` within which a followed match's way back must return (step
#: 0): a match that follows its prediction returns to within 0.03 px of its start (99 % of
#: them, on real frames moving steadily); one that drifted onto a half-occluded patch came
#: back 0.95 px away, inside the bound, 1.2 px off the truth. Those are left to the search.
FOLLOW_FB = 0.25
#: where step 0's Gauss-Newton from a prediction of no motion (a track's first pair) leaves
#: the pixel's reach of its start (the refinement's patch of frame t+1 holds a pixel's margin)
#: for a point within this many px of it, and no coarser level can run (a template within
#: 2^k (n + 1) px of the frame's edge does not fit level k), it runs once more from that
#: point, as Lucas-Kanade iterates past a pixel at one level, and takes a match within this
#: many px of the start, which the way back then checks (0: never). On the bench's first pair
#: (the scene moving 1.3 px), 10 features 5 to 9 px from the edge were searched coarse to fine
#: for it: 185 -> 159 us. Beyond a couple of pixels the first step from no motion is no
#: guide: on the five sources moved 1.5 to 4.3 px (120 first pairs, 32606 matches) a second
#: run that went anywhere took 4 more matches off by more than 2 px than the search (31
#: against 27, lookalikes near the edge), bounded here 1 (28). Nor from a measured
#: prediction: one that missed by several px (a shake) lets such a second run converge onto a
#: lookalike that its way back confirms (on Urban2's shake through a rolling shutter, 6
#: features 7 px off), where the search would have found the feature or rejected it
FOLLOW_STRAY_PX = 2.0
#: a followed match within this many px of a prediction from measured motion (its velocity,
#: or a new feature's frame's motion) is taken without its way back, which returns such a
#: match to within hundredths of a pixel (79 % of the bench's held features; the scoreboard
#: unchanged, the held frames 7 % faster). A track's first pair is always checked: its
#: prediction is no motion, not a measurement, and on Urban2's facades Gauss-Newton brought
#: 2 features to rest near their start while the scene moved 3.5 px
FOLLOW_NEAR = 0.25
#: the wide window's estimate is taken where, at the correlation window's estimate, each side
#: of its ring has a mean squared residual at most this many times its centre's (plus
#: noise's; :func:`_widen`)
STRADDLE = 2.0
#: ... and where a side does not, it is still taken where each side fits the wide estimate
#: at most this many times as badly as its centre (plus noise's; :func:`_widen`)
EVEN = 1.25
#: :func:`_ring_fit`'s bilinear weights are in 1/BILINEAR_ONE (a residual of 255 grey
#: levels, squared, still fits int32: (128 * 255)^2 < 2^31)
BILINEAR_ONE = 128
#: what one reduction (:func:`_reduce`: the kernel [1 4 6 4 1]^2 / 256) leaves of the
#: variance of white noise: (sum of the squared weights)^2
NOISE_GAIN = (70.0 / 256.0) ** 2


@dataclass(frozen=True, eq=False)
class Pyramid:
    """A frame and its reductions, in one flat buffer.

    Attributes
    ----------
    data : (sum of h_k w_k,) uint8, C-contiguous: level 0 (the frame) first, then each
        reduction, row after row. One buffer rather than a list of arrays: a numba typed List
        is slow to pass to a kernel and to build, and slow to compile.
    geo : (levels, 3) int64: offset in ``data``, height and width of each level; shared by
        the pyramids of frames of one size (:func:`_layout`): never written to.
    shapes : (height, width) of each level.
    """

    data: np.ndarray
    geo: np.ndarray
    shapes: tuple[tuple[int, int], ...]

    @property
    def levels(self) -> int:
        return len(self.shapes)

    def level(self, k: int) -> np.ndarray:
        """Level k, (h, w) uint8 (a view into :attr:`data`)."""
        o, h, w = (int(v) for v in self.geo[k])
        return self.data[o:o + h * w].reshape(h, w)


def build_pyramid(frame: np.ndarray, levels: int) -> Pyramid:
    """``levels`` levels of an (H, W) uint8 frame (fewer where a side would fall below 4 px):
    level k + 1 is level k filtered by the binomial [1 4 6 4 1]^2 / 256 and every other pixel
    kept (:func:`_reduce`), so that its pixel (x, y) lies at (2x, 2y) of level k."""
    if levels < 1:
        raise ValueError(f"levels={levels} must be at least 1")
    frame = np.ascontiguousarray(frame, np.uint8)
    if frame.ndim != 2:
        raise ValueError(f"expected an (H, W) frame, got shape {frame.shape}")
    geo, shapes, size = _layout(frame.shape, levels)
    data = np.empty(size, np.uint8)
    _build(frame, data, geo)
    return Pyramid(data, geo, shapes)


@functools.lru_cache(maxsize=8)
def _layout(shape: tuple[int, int], levels: int
            ) -> tuple[np.ndarray, tuple[tuple[int, int], ...], int]:
    """The table of levels (:attr:`Pyramid.geo`), their shapes and the pyramid's size in
    bytes for frames of ``shape``: the same for every frame of a run, so made once (building
    it took ~1/3 of :func:`build_pyramid`, ~10 us a frame). The table is shared by those
    frames' pyramids and must not be written to."""
    shapes = [(int(shape[0]), int(shape[1]))]
    while len(shapes) < levels and min(shapes[-1]) >= 8:
        h, w = shapes[-1]
        shapes.append(((h + 1) // 2, (w + 1) // 2))
    geo = np.empty((len(shapes), 3), np.int64)
    offset = 0
    for k, (h, w) in enumerate(shapes):
        geo[k] = offset, h, w
        offset += h * w
    return geo, tuple(shapes), offset


@nb.njit(cache=True, nogil=True)
def _level(data, geo, k):  # pragma: no cover - numba
    """Level k of a pyramid's flat buffer, (h, w) C-contiguous (a view, no copy)."""
    o = geo[k, 0]
    return data[o:o + geo[k, 1] * geo[k, 2]].reshape((geo[k, 1], geo[k, 2]))


@nb.njit(**NO_NRT)
def _refine_at(pdata, cdata, geo, k, ax, ay, x0, y0, n, scratch, third):  # pragma: no cover
    """:func:`.ssd._refine_with` on level k of two pyramids' buffers, its views made here.

    Compiled without numba's runtime (``_nrt=False``), as the kernels it calls: a view that
    :func:`_level` returns is a new reference, an atomic increment and decrement of its
    buffer's count, and the two levels' for each feature followed were ~20 % of those a frame
    made, which in all took a third of the default tracker's time (perf on the bench's held
    frames). Nothing here allocates or keeps an array."""
    o = geo[k, 0]
    size = geo[k, 1] * geo[k, 2]
    prev = pdata[o:o + size].reshape((geo[k, 1], geo[k, 2]))
    curr = cdata[o:o + size].reshape((geo[k, 1], geo[k, 2]))
    return _refine_with(prev, curr, ax, ay, x0, y0, n, scratch, third)


@nb.njit(cache=True, nogil=True)
def _build(frame, data, geo):  # pragma: no cover - numba
    h, w = frame.shape
    flat = frame.ravel()
    for q in range(h * w):
        data[q] = flat[q]
    # a row's column sums, its even and its odd columns apart (_reduce); the widest level's
    even = np.empty(w // 2 + 4, np.uint16)
    odd = np.empty(w // 2 + 4, np.uint16)
    for k in range(1, geo.shape[0]):
        _reduce(data, geo[k - 1, 0], geo[k - 1, 1], geo[k - 1, 2], geo[k, 0], geo[k, 1],
                geo[k, 2], even, odd)


@nb.njit(**NO_NRT, inline="always")
def _column(r0, r1, r2, r3, r4, x):  # pragma: no cover - numba
    """The vertical [1 4 6 4 1] of column x of five rows (uint8), in uint16 (:func:`_reduce`)."""
    u16 = np.uint16
    return u16(u16(r0[x]) + u16(r4[x]) + u16(4) * (u16(r1[x]) + u16(r3[x]))
               + u16(6) * u16(r2[x]))


@nb.njit(**NO_NRT)
def _reduce(data, so, h, w, do, dh, dw, even, odd):  # pragma: no cover - numba
    """One pyramid reduction (Burt and Adelson's, as ``cv2.pyrDown``) in a pyramid's flat
    buffer: the (dh, dw) level at offset ``do`` is the (h, w) level at ``so`` filtered by
    the binomial [1 4 6 4 1]^2 / 256 at (2x, 2y), edges replicated, rounded.

    The vertical filter of five source rows, edge-padded by two each side, then the
    horizontal one at every other column. In uint16 (16 lanes a vector where uint32 had 8;
    2x faster): a column sum is at most 16 * 255 and a pixel's at most 16 * 16 * 255 + 128 =
    65408, so that nothing wraps, and the sums are cast to uint16 before the shift, so that
    LLVM keeps them in 16 bits. The column sums go to ``even`` and ``odd`` (column 2i - 2 of
    the padded row at even[i], 2i - 1 at odd[i]), so that the horizontal filter reads
    contiguous lanes rather than every other one; no numba runtime (``_nrt=False``): the
    rows are slices of the buffer, whose views took atomic reference counts, six a row.
    10.3 -> 6.4 us a 256 x 256 frame's pyramid of 3 levels, back to back."""
    u16 = np.uint16
    half = (w + 1) // 2  # the even columns
    for y in range(dh):
        c = 2 * y
        o0 = so + max(c - 2, 0) * w
        o1 = so + max(c - 1, 0) * w
        o2 = so + c * w
        o3 = so + min(c + 1, h - 1) * w
        o4 = so + min(c + 2, h - 1) * w
        r0 = data[o0:o0 + w]
        r1 = data[o1:o1 + w]
        r2 = data[o2:o2 + w]
        r3 = data[o3:o3 + w]
        r4 = data[o4:o4 + w]
        ev = even[1:]
        od = odd[1:]
        for i in range(w // 2):
            ev[i] = _column(r0, r1, r2, r3, r4, 2 * i)
            od[i] = _column(r0, r1, r2, r3, r4, 2 * i + 1)
        if w % 2:
            even[half] = _column(r0, r1, r2, r3, r4, w - 1)
        # the padding: columns -2 and -1 repeat column 0; w and w + 1 repeat w - 1
        even[0] = odd[0] = even[1]
        if w % 2:
            odd[half] = even[half + 1] = even[half]
        else:
            even[half + 1] = odd[half + 1] = odd[half]
        # dst[y, x] from the padded columns 2x - 2 to 2x + 2: even[x], odd[x], even[x + 1],
        # odd[x + 1], even[x + 2]
        out = data[do + y * dw:do + (y + 1) * dw]
        ea = even[0:dw]
        eb = even[1:dw + 1]
        ec = even[2:dw + 2]
        oa = odd[0:dw]
        ob = odd[1:dw + 1]
        for x in range(dw):
            out[x] = u16(ea[x] + ec[x] + u16(4) * (oa[x] + ob[x]) + u16(6) * eb[x]
                         + u16(128)) >> 8


@nb.njit(cache=True, nogil=True)
def _descend(prev, curr, ax, ay, cx, cy, n, wts, uniform, steps,
             seen):  # pragma: no cover - numba
    """Descent on the integer displacements from (cx, cy): the 3x3 around the centre are
    scored (each abandoned once above the best; a score is kept for the next step) and the
    best becomes the centre, until the centre is the best. Ties keep the centre, else the
    first in row-major order.

    Returns (status, qx, qy, S): OK; CUT when the minimum touches an image edge (it may be a
    piece of one outside); LEFT when the template or the first window leaves the image;
    RUNAWAY after ``steps`` moves. ``seen``: int64 scratch of (2 steps + 3)^2.
    """
    h, w = prev.shape
    if (ax - n < 0 or ay - n < 0 or ax + n >= w or ay + n >= h or cx - n < 0 or cy - n < 0
            or cx + n >= w or cy + n >= h):
        return LEFT, cx, cy, np.inf
    pf = prev.ravel()
    cf = curr.ravel()
    # scores around (cx, cy) by offset, -1 where not scored in full (an abandoned sum only
    # bounds S from below, by the best of its moment)
    seen[:, :] = -1
    o = steps + 1
    x = cx
    y = cy
    best = _ssd_at(pf, cf, w, ax, ay, x, y, n, wts, uniform, BIG)
    seen[o, o] = best
    for _ in range(steps + 1):
        bx = x
        by = y
        edge = False
        for dy in range(-1, 2):
            for dx in range(-1, 2):
                if dx == 0 and dy == 0:
                    continue
                qx = x + dx
                qy = y + dy
                if qx - n < 0 or qy - n < 0 or qx + n >= w or qy + n >= h:
                    edge = True
                    continue
                known = seen[qy - cy + o, qx - cx + o]
                if known >= 0:
                    v = known
                else:
                    v = _ssd_at(pf, cf, w, ax, ay, qx, qy, n, wts, uniform, best)
                    if v <= best:
                        seen[qy - cy + o, qx - cx + o] = v
                if v < best:
                    best = v
                    bx = qx
                    by = qy
        if bx == x and by == y:
            return (CUT if edge else OK), x, y, float(best)
        x = bx
        y = by
    return RUNAWAY, x, y, float(best)


@nb.njit(**NO_NRT)
def _starting(anchors, pending, n, shape, k):  # pragma: no cover - numba
    """How many ``pending`` features can start at level k of the given shape: at a coarse
    level, those whose template fits it (the others start a level finer; a search for them
    alone would only say so, at the fixed cost of a search: ~3 us, most of what an edge
    feature cost); at the frame's level, every pending one (whose status it sets)."""
    h, w = shape
    count = 0
    for f in range(anchors.shape[0]):
        if pending[f] and (k == 0 or (n <= anchors[f, 0] < w - n
                                      and n <= anchors[f, 1] < h - n)):
            count += 1
    return count


@nb.njit(cache=True, nogil=True)
def _match(pdata, cdata, geo, pts, preds, active, n, s, wts, exhaustive, ratio, allowance,
           reject_border, subpixel, scratch, seen, out_pos, out_ssd,
           out_status, budget):  # pragma: no cover - numba
    """Steps 1 and 2 of the module notes for the ``active`` features at ``pts`` (float x, y)
    predicted at ``preds``: their position ``out_pos`` in frame t+1, S of Eq. (1) at its
    nearest pixel ``out_ssd`` and ``out_status`` (OK, or why not found). ``pdata``,
    ``cdata``, ``geo``: the pyramids of frames t and t+1 (:class:`Pyramid`).

    A feature's match is carried as the displacement of its template: at its start level k
    the integer one of the search, d_k = q_k - round(p / 2^k). Refining at level j < k starts
    from 2 d_(j+1): with ``subpixel``, by Gauss-Newton (:func:`.ssd._refine`, the template at
    p / 2^j), which gives sub-pixel displacements (Bouguet's scheme), falling back to the
    integer descent (:func:`_descend`) where it cannot run; without, by the descent.
    """
    levels = geo.shape[0]
    n_feat = pts.shape[0]
    uniform, _, _ = _weights_info(wts)
    at = np.empty(n_feat, np.int64)  # the level of the feature's match; -1 none yet
    disp = np.zeros((n_feat, 2), np.float64)  # its displacement there
    pending = np.empty(n_feat, np.bool_)
    for f in range(n_feat):
        at[f] = -1
        pending[f] = active[f]
        if active[f]:
            out_status[f] = LEFT
            out_ssd[f] = np.inf
            out_pos[f, 0] = np.nan
            out_pos[f, 1] = np.nan
    anchors = np.empty((n_feat, 2), np.int64)
    centers = np.empty((n_feat, 2), np.int64)
    lq = np.zeros((n_feat, 2), np.int64)
    lssd = np.empty(n_feat, np.float64)
    lstatus = np.empty(n_feat, np.int8)
    for k in range(levels - 1, -1, -1):
        prev = _level(pdata, geo, k)
        curr = _level(cdata, geo, k)
        scale = 2.0 ** k
        for f in range(n_feat):
            # the active features' only (the others' are never read): on a frame whose
            # features follow, a few of ~100, and this loop over all of them was most of
            # a call's ~3 us (one a frame, and one for each retry and way back)
            if active[f]:
                for c in range(2):
                    anchors[f, c] = int(np.rint(pts[f, c] / scale))
                    centers[f, c] = int(np.rint(preds[f, c] / scale))
        starting = _starting(anchors, pending, n, prev.shape, k)
        # refine the matches of the level above, their displacement doubled
        for f in range(n_feat):
            if at[f] != k + 1:
                continue
            ax = anchors[f, 0]
            ay = anchors[f, 1]
            dx = 2.0 * disp[f, 0]
            dy = 2.0 * disp[f, 1]
            done = False
            if subpixel:
                good, x, y = _refine_with(prev, curr, ax, ay, ax + dx, ay + dy, n, scratch,
                                          THIRD if k == 0 else NO_THIRD)
                if good:
                    disp[f, 0] = x - ax
                    disp[f, 1] = y - ay
                    done = True
            if not done:
                st, qx, qy, ssd = _descend(prev, curr, ax, ay, ax + int(np.rint(dx)),
                                           ay + int(np.rint(dy)), n, wts, uniform,
                                           DESCENT_STEPS, seen)
                if st != OK:
                    out_status[f] = st
                    at[f] = -2
                    continue
                x = float(qx)
                y = float(qy)
                if subpixel and k == 0:
                    x, y = _from_integer(prev, curr, ax, ay, qx, qy, n, wts, uniform, ssd,
                                         scratch)
                disp[f, 0] = x - ax
                disp[f, 1] = y - ay
            at[f] = k
        if starting == 0:
            continue
        # start the features not matched yet; a failed start starts again a level finer.
        # Each reduction averages the noise: its variance shrinks by NOISE_GAIN a level
        _search_level(prev, curr, anchors, centers, pending, n, s, wts, exhaustive, ratio,
                      allowance * NOISE_GAIN ** k, lq, lssd, lstatus, budget)
        for f in range(n_feat):
            if not pending[f]:
                continue
            st = lstatus[f]
            good = st == OK or (st == BORDER and not reject_border)
            if not good and k > 0 and st != OVER:
                continue
            pending[f] = False
            if not good:
                out_status[f] = st
                at[f] = -2
                continue
            x = float(lq[f, 0])
            y = float(lq[f, 1])
            if subpixel and k == 0:
                x, y = _from_integer(prev, curr, anchors[f, 0], anchors[f, 1], lq[f, 0],
                                     lq[f, 1], n, wts, uniform, lssd[f], scratch)
            disp[f, 0] = x - anchors[f, 0]
            disp[f, 1] = y - anchors[f, 1]
            at[f] = k
    # positions, and S of Eq. (1) at the nearest pixel (the residual test)
    prev = _level(pdata, geo, 0)
    curr = _level(cdata, geo, 0)
    h, w = prev.shape
    pf = prev.ravel()
    cf = curr.ravel()
    for f in range(n_feat):
        if at[f] != 0:
            continue
        ax = int(np.rint(pts[f, 0]))
        ay = int(np.rint(pts[f, 1]))
        qx = ax + int(np.rint(disp[f, 0]))
        qy = ay + int(np.rint(disp[f, 1]))
        if qx - n < 0 or qy - n < 0 or qx + n >= w or qy + n >= h:
            out_status[f] = CUT  # the window reached past the image's edge
            continue
        out_status[f] = OK
        out_pos[f, 0] = pts[f, 0] + disp[f, 0]
        out_pos[f, 1] = pts[f, 1] + disp[f, 1]
        out_ssd[f] = float(_ssd_at(pf, cf, w, ax, ay, qx, qy, n, wts, uniform, BIG))


@nb.njit(cache=True, nogil=True)
def _track_frame(pdata, cdata, geo, pts, preds, held, follow, followed, n, s, wts, exhaustive,
                 ratio, allowance, reject_border, guided_retry, fb_bound, consensus, dominant,
                 dominant_follow, reach, depart, arbiter, affine_fit, rescue_fit, rescue_near,
                 subpixel, wide, acc, straddle, even, floor, budget, out_pos, out_ssd,
                 out_status):  # pragma: no cover - numba
    """The whole of :func:`track_pyramid` (steps 0 to 7 of the module notes), returning how
    many were found; ``acc``: the integer type of the sub-pixel sums
    (:func:`.ssd.refine_acc`); ``dominant``, ``dominant_follow``, ``reach``, ``depart``,
    ``arbiter``, ``affine_fit``, ``rescue_fit`` and ``rescue_near``: DOMINANT_PX,
    DOMINANT_FOLLOW_PX, PERIOD_REACH, PERIOD_DEPART_PX, the wide window's half-width where
    WIDE_ARBITER (else 0), AFFINE_FIT_PX, RESCUE_FIT_PX and RESCUE_AFFINE_NEAR (read where it
    is called, so that a test can turn steps 5b, its Gauss-Newton, its period test and its
    wide window, 7, 5c and its affine fit off); ``budget``:
    (1,) int64, what is left of the frame's searches
    (:data:`FRAME_WORK`), drawn on here.
    Returns -1, having done nothing, where a point or prediction is not finite within
    +-MAX_COORD (NaN fails the comparison too): one given to the search indexed memory at
    random (SIGSEGV)."""
    n_feat = pts.shape[0]
    for f in range(n_feat):
        for c in range(2):
            if not (abs(pts[f, c]) <= MAX_COORD and abs(preds[f, c]) <= MAX_COORD):
                return -1
    for f in range(n_feat):
        out_pos[f, 0] = np.nan
        out_pos[f, 1] = np.nan
        out_ssd[f] = np.inf
        out_status[f] = LEFT
    if n_feat == 0:
        return 0
    uniform, _, _ = _weights_info(wts)
    scratch = _refine_scratch(wts, acc)
    seen = np.empty((2 * DESCENT_STEPS + 3, 2 * DESCENT_STEPS + 3), np.int64)
    # 0. the held features that follow their prediction; the others (active) coarse to fine
    active = np.ones(n_feat, np.bool_)
    if follow and subpixel and fb_bound > 0.0:
        _follow(pdata, cdata, geo, pts, preds, held, n, wts, fb_bound, scratch, active,
                out_pos, out_ssd, out_status)
    for f in range(n_feat):
        followed[f] = not active[f]
    _match(pdata, cdata, geo, pts, preds, active, n, s, wts, exhaustive, ratio, allowance,
           reject_border, subpixel, scratch, seen, out_pos, out_ssd, out_status, budget)
    # each feature's predicted displacement (loops rather than array expressions here and
    # below: each of those compiles into a kernel of its own)
    offset = np.empty((n_feat, 2), np.float64)
    # 3. guided retry around the frame's dominant motion
    found = 0
    for f in range(n_feat):
        offset[f, 0] = preds[f, 0] - pts[f, 0]
        offset[f, 1] = preds[f, 1] - pts[f, 1]
        found += out_status[f] == OK
    gx = gy = 0.0
    if guided_retry and MIN_GUIDES <= found < n_feat:
        # the guide, only where some feature may be retried around it (most frames none)
        gx, gy = _dominant(pts, out_pos, out_status)
    retries = 0
    retry = np.zeros(n_feat, np.bool_)
    for f in range(n_feat):
        st = out_status[f]
        # a window that left the image around a prediction the frame's motion contradicts
        # (a bump: the step back after a jump put 18 of 50 predictions off the frame, whose
        # features were in it) is searched around that motion too
        broke = abs(offset[f, 0] - gx) > DOMINANT_PX or abs(offset[f, 1] - gy) > DOMINANT_PX
        retry[f] = (st == CUT or st == BORDER or st == AMBIGUOUS or st == RUNAWAY
                    or (st == LEFT and broke))
        retries += retry[f]
    if guided_retry and found >= MIN_GUIDES and retries > 0:
        guided = np.empty((n_feat, 2), np.float64)
        for f in range(n_feat):
            guided[f, 0] = pts[f, 0] + gx
            guided[f, 1] = pts[f, 1] + gy
        pos2 = np.empty((n_feat, 2), np.float64)
        ssd2 = np.empty(n_feat, np.float64)
        st2 = np.empty(n_feat, np.int8)
        _match(pdata, cdata, geo, pts, guided, retry, n, s, wts, exhaustive, ratio, allowance,
               reject_border, subpixel, scratch, seen, pos2, ssd2, st2, budget)
        _take(retry, st2, ssd2, pos2, out_status, out_ssd, out_pos)
        for f in range(n_feat):
            if retry[f]:
                offset[f, 0] = gx
                offset[f, 1] = gy
    prev = _level(pdata, geo, 0)
    curr = _level(cdata, geo, 0)
    # 4. forward-backward check: back from frame t+1 to frame t, the prediction mirrored,
    # held to the same tests as the forward search
    if fb_bound > 0.0:
        check = np.empty(n_feat, np.bool_)
        back = np.zeros((n_feat, 2), np.float64)
        mirrored = np.zeros((n_feat, 2), np.float64)
        checks = 0
        for f in range(n_feat):
            check[f] = out_status[f] == OK and active[f]
            if check[f]:
                checks += 1
                for c in range(2):
                    back[f, c] = out_pos[f, c]
                    mirrored[f, c] = out_pos[f, c] - offset[f, c]
        if checks > 0 and subpixel:
            # the coarse search back, then Gauss-Newton at the frame's level from where the
            # feature started; the full way back only where that cannot run (_back_check)
            checks = _back_check(pdata, cdata, geo, pts, back, mirrored, check, n, s, wts,
                                 exhaustive, ratio, allowance, reject_border, scratch,
                                 fb_bound, out_status, budget)
        if checks > 0:
            posb = np.empty((n_feat, 2), np.float64)
            ssdb = np.empty(n_feat, np.float64)
            stb = np.empty(n_feat, np.int8)
            _match(cdata, pdata, geo, back, mirrored, check, n, s, wts, exhaustive, ratio,
                   allowance, reject_border, subpixel, scratch, seen, posb, ssdb, stb, budget)
            for f in range(n_feat):
                if not check[f]:
                    continue
                ex = posb[f, 0] - pts[f, 0]
                ey = posb[f, 1] - pts[f, 1]
                if stb[f] == OVER:
                    out_status[f] = OVER  # not checked: not trusted
                elif stb[f] != OK or ex * ex + ey * ey > fb_bound * fb_bound:
                    out_status[f] = FB
    # 5. consensus: a match must move as its nearest neighbours do
    judged = np.empty(0, np.int64)
    judged_near = np.empty((0, NEIGHBOURS), np.int64)
    if consensus > 0.0:
        judged, judged_near = _consensus(pts, out_pos, out_status, consensus)
    # 5b. the frame's dominant motion, and the texture's period, as a second minimum
    # (followed there: sub-pixel only)
    if ratio > 0.0:
        apart = dominant_follow if subpixel else np.inf
        _dominant_alternative(pdata, cdata, geo, pts, out_pos, out_ssd, out_status, active, n,
                              wts, uniform, ratio, allowance, dominant, apart, arbiter, scratch)
        if reach > 0 and apart < np.inf:
            _period_alternative(pdata, cdata, geo, pts, out_pos, out_status, active, offset, n,
                                wts, uniform, ratio, allowance, depart, apart, arbiter, reach,
                                scratch, budget)
    # 5c. a match rejected where its neighbours move as one surface: followed from their motion
    if rescue_fit > 0.0 and fb_bound > 0.0 and consensus > 0.0 and subpixel:
        _rescue(pdata, cdata, geo, pts, out_pos, out_ssd, out_status, n, wts, scratch,
                fb_bound, rescue_fit, rescue_near)
    # 6. the wide window's sub-pixel estimate, where its neighbourhood moves as its centre
    ok = np.empty(n_feat, np.bool_)
    found = 0
    for f in range(n_feat):
        ok[f] = out_status[f] == OK
        found += ok[f]
        if not ok[f]:
            out_pos[f, 0] = np.nan
            out_pos[f, 1] = np.nan
            out_ssd[f] = np.inf
    took = np.zeros(n_feat, np.bool_)
    cen = np.empty((n_feat, 8), np.float64)
    if subpixel and wide > n:
        _widen(prev, curr, pts, n, wide, acc, ok, out_pos, straddle, even, floor, took, cen)
    # 7. each estimate is of the motion at its window's centroid: corrected to the feature's
    # point by its neighbourhood's scale and rotation
    if subpixel and affine_fit > 0.0:
        _affine_correction(prev, pts, out_pos, out_status, took, cen, n, wts, uniform,
                           affine_fit, judged, judged_near)
    return found


@nb.njit(cache=True, nogil=True)
def _follow(pdata, cdata, geo, pts, preds, held, n, wts, fb_bound, scratch, active, out_pos,
            out_ssd, out_status):  # pragma: no cover - numba
    """Step 0: the ``held`` features (tracked in the frame before) followed from their
    prediction by Gauss-Newton alone: at the frame's own level, and where that does not
    converge within a pixel of the prediction, coarse to fine from the coarsest level whose
    pixels hold the template (Bouguet's pyramidal scheme; a level where it cannot run or does
    not converge starts again from the prediction a level finer). A match whose way back
    (Gauss-Newton in frame t from the start) returns within FOLLOW_FB ``fb_bound`` px is taken
    (``active`` cleared), as is one found at the frame's level within FOLLOW_NEAR of a
    prediction from measured motion (not tried back); any other is left to the
    coarse-to-fine search (``active`` kept).

    Unless most held features follow: then the frame broke the prediction (a jerk, a turn),
    and the few that converged may have done so onto a lookalike near their prediction, which
    the way back confirms as well (tried: a 9 px jump the other way, 2 of 74 "followed" to a
    wrong place, which only the consensus caught); every feature is then searched."""
    uniform, _, _ = _weights_info(wts)
    took = np.zeros(pts.shape[0], np.bool_)
    count, taken = _follow_each(pdata, cdata, geo, pts, preds, held, n, wts, uniform, fb_bound,
                                scratch, took, out_pos, out_ssd)
    if 2 * taken <= count:
        return
    for f in range(pts.shape[0]):
        if took[f]:
            active[f] = False
            out_status[f] = OK


@nb.njit(**NO_NRT)
def _follow_each(pdata, cdata, geo, pts, preds, held, n, wts, uniform, fb_bound, scratch, took,
                 out_pos, out_ssd):  # pragma: no cover - numba
    """:func:`_follow`'s features, each followed and checked: ``took[f]`` set, ``out_pos[f]``
    and ``out_ssd[f]`` written for each taken. Returns (held features, taken).

    Without numba's runtime (``_nrt=False``): nothing here allocates or keeps an array, and
    with it each feature's views took atomic reference counts (see :func:`_refine_at`)."""
    o = geo[0, 0]
    h = geo[0, 1]
    w = geo[0, 2]
    pf = pdata[o:o + h * w]
    cf = cdata[o:o + h * w]
    prev = pf.reshape((h, w))
    curr = cf.reshape((h, w))
    n_feat = pts.shape[0]
    count = 0
    taken = 0
    for f in range(n_feat):
        if not held[f]:
            continue
        count += 1
        ax = int(np.rint(pts[f, 0]))
        ay = int(np.rint(pts[f, 1]))
        ox = preds[f, 0] - pts[f, 0]  # the predicted displacement
        oy = preds[f, 1] - pts[f, 1]
        good, first, x, y = _follow_one(pdata, cdata, geo, pts[f, 0], pts[f, 1], ox, oy, n,
                                        scratch)
        if not good:
            continue
        px = pts[f, 0] + (x - ax)
        py = pts[f, 1] + (y - ay)
        # the way back (FOLLOW_NEAR: not for a match where measured motion predicted it;
        # a track's first pair predicts no motion, exactly 0): the match's template in
        # frame t+1, from the start in frame t
        near = (first and (ox != 0.0 or oy != 0.0)
                and (px - preds[f, 0]) ** 2 + (py - preds[f, 1]) ** 2 <= FOLLOW_NEAR ** 2)
        if not near and not _returns(prev, curr, pts[f, 0], pts[f, 1], px, py, n, scratch,
                                     FOLLOW_FB * fb_bound):
            continue
        if not _keep(pf, cf, w, h, ax, ay, x, y, px, py, n, wts, uniform, f, out_pos, out_ssd):
            continue
        took[f] = True
        taken += 1
    return count, taken


@nb.njit(**NO_NRT)
def _returns(prev, curr, sx, sy, px, py, n, scratch, lim):  # pragma: no cover - numba
    """The way back of a match followed by Gauss-Newton (steps 0 and 5c): the template at
    (px, py) of frame t+1 (``curr``), refined in frame t (``prev``) from the start (sx, sy),
    returns to within ``lim`` px of it."""
    bx = int(np.rint(px))
    by = int(np.rint(py))
    good, xb, yb = _refine_with(curr, prev, bx, by, bx + (sx - px), by + (sy - py), n, scratch,
                                NO_THIRD)
    if not good:
        return False
    ex = px + (xb - bx) - sx
    ey = py + (yb - by) - sy
    return ex * ex + ey * ey <= lim * lim


@nb.njit(**NO_NRT)
def _keep(pf, cf, w, h, ax, ay, x, y, px, py, n, wts, uniform, f, out_pos,
          out_ssd):  # pragma: no cover - numba
    """Feature f's match (px, py), its template at (ax, ay) of frame t found at (x, y) of
    frame t+1, written to ``out_pos`` with S at the nearest whole pixel (``out_ssd``) where
    the window fits frame t+1 there (steps 0 and 5c); False where it does not."""
    qx = ax + int(np.rint(x - ax))
    qy = ay + int(np.rint(y - ay))
    if qx - n < 0 or qy - n < 0 or qx + n >= w or qy + n >= h:
        return False
    out_pos[f, 0] = px
    out_pos[f, 1] = py
    out_ssd[f] = float(_ssd_at(pf, cf, w, ax, ay, qx, qy, n, wts, uniform, BIG))
    return True


@nb.njit(**NO_NRT)
def _follow_one(pdata, cdata, geo, fx, fy, ox, oy, n, scratch):  # pragma: no cover - numba
    """Gauss-Newton from the displacement (ox, oy) of the feature at (fx, fy) (steps 0 and
    5c): at the frame's level, and where that does not converge within a pixel, coarse to
    fine from the coarsest level whose pixels hold the template (a level where it cannot run
    or does not converge starts again from (ox, oy) a level finer); from no motion (ox = oy =
    0), where the first call strayed past its pixel, to within FOLLOW_STRAY_PX, and no coarser
    level helped, once more at the frame's level from there, its match taken within
    FOLLOW_STRAY_PX of the start. Returns (converged,
    converged at the frame's level first, x, y): (x, y) the match of the template centred at
    the rounded point. One call of the refinement in the loop: LLVM inlines each call
    (compile time)."""
    levels = geo.shape[0]
    ax = int(np.rint(fx))
    ay = int(np.rint(fy))
    k = 0
    first = True
    have = False
    dx = dy = 0.0
    strayed = False  # the first attempt left its pixel's reach, for (sx, sy) (FOLLOW_STRAY_PX)
    retried = False
    sx = sy = 0.0
    while True:
        scale = 2.0 ** k
        kx = int(np.rint(fx / scale))
        ky = int(np.rint(fy / scale))
        if have:
            dx *= 2.0
            dy *= 2.0
        elif k == 0 and not first:
            if not strayed:
                break  # no coarse level helped: the first attempt's own call, which failed
            strayed = False  # once more, from where the first attempt strayed to
            retried = True
            dx = sx
            dy = sy
        else:
            dx = ox / scale
            dy = oy / scale
        x0 = kx + dx
        y0 = ky + dy
        have, xk, yk = _refine_at(pdata, cdata, geo, k, kx, ky, x0, y0, n,
                                  scratch, THIRD if k == 0 else NO_THIRD)
        if retried and (xk - kx) ** 2 + (yk - ky) ** 2 > FOLLOW_STRAY_PX ** 2:
            have = False  # beyond what the first step from no motion can be trusted for
        if have:
            dx = xk - kx
            dy = yk - ky
        elif (k == 0 and first and ox == 0.0 and oy == 0.0 and (xk != x0 or yk != y0)
              and abs(xk - x0) <= FOLLOW_STRAY_PX and abs(yk - y0) <= FOLLOW_STRAY_PX):
            strayed = True
            sx = xk - kx
            sy = yk - ky
        if k > 0:
            k -= 1
        elif have or not first or levels == 1:
            break
        else:
            first = False
            k = levels - 1
    return have, first, ax + dx, ay + dy


@nb.njit(**NO_NRT)
def _take(which, status, ssd, pos, out_status, out_ssd, out_pos):  # pragma: no cover - numba
    """The results (``status``, ``ssd``, ``pos``) of a second search where ``which``."""
    for f in range(which.shape[0]):
        if which[f]:
            out_status[f] = status[f]
            out_ssd[f] = ssd[f]
            out_pos[f, 0] = pos[f, 0]
            out_pos[f, 1] = pos[f, 1]


@nb.njit(cache=True, nogil=True)
def _rescue(pdata, cdata, geo, pts, out_pos, out_ssd, out_status, n, wts, scratch, fb_bound,
            fit, affine_near):  # pragma: no cover - numba
    """Step 5c: each match rejected by a test of its search (BORDER, AMBIGUOUS, RUNAWAY, FB,
    DISAGREES) whose NEIGHBOURS nearest matches move as one surface (their displacements fit
    a similarity to within ``fit`` px rms, else, with ``affine_near`` more than NEIGHBOURS,
    the ``affine_near`` nearest fit an affine map to within ``fit``) is followed by
    Gauss-Newton from the displacement that fit gives at its point (:func:`_follow_one`,
    coarse to fine where it does not converge at the frame's level). It is taken where it
    lands within RESCUE_NEAR_PX (or 3 rms, where larger) of that displacement and its way
    back returns to within FOLLOW_FB ``fb_bound`` of its start, as a followed match's must
    (:func:`_returns`); else it keeps its status. Landing that near its neighbours' motion,
    it cannot be a lookalike farther off; the way back and the residual test
    (:mod:`.tracker`) see an occluded patch.

    A search fails where its coarse level aliases a repetitive texture or its reach misses a
    motion the prediction did not foresee (a shaking camera: every frame jolted by up to 6 px
    at random, the prediction 12 px off at the median), and the way back or the consensus
    then rejects a match that Lucas-Kanade from the neighbours' motion finds to a few
    hundredths of a pixel. Followed from there, as Lucas-Kanade is, it is kept.

    A rolling shutter that shakes exposes each row at its own jolt: a neighbourhood's motion
    shears, no similarity fits it, and RubberWhale's shake with a readout of 0.9 of the frame
    interval (the scoreboard's) kept 0.27 of its first frame's features against LK's 0.72;
    with the affine fit 0.47. Over NEIGHBOURS points an affine fits nearly anything (Urban2's
    pair, 500 features: 12 of 411 pairs off by more than 2 px -> 17 of 443); over
    ``affine_near`` (or as many matches as there are, fewer) it must fit (15 more found, 1
    more off).

    Returns how many were rescued."""
    n_feat = pts.shape[0]
    rejected = 0
    for f in range(n_feat):
        st = out_status[f]
        rejected += (st == BORDER or st == AMBIGUOUS or st == RUNAWAY or st == FB
                     or st == DISAGREES)
    if rejected == 0:  # most frames: nothing to rescue, no list of matches made
        return 0
    idx, xs, ys, dxs, dys = _matches(pts, out_pos, out_status)
    c = idx.shape[0]
    if c <= NEIGHBOURS:
        return 0
    uniform, _, _ = _weights_info(wts)
    h = geo[0, 1]
    w = geo[0, 2]
    pf = pdata[0:h * w]
    cf = cdata[0:h * w]
    prev = pf.reshape((h, w))
    curr = cf.reshape((h, w))
    k = max(NEIGHBOURS, min(affine_near, c))  # the nearest matches listed
    near = np.empty(k, np.int64)
    near_d = np.empty(k, np.float64)
    last = k - 1
    fit_pts = np.empty((4, k), np.float64)
    count = 0
    for f in range(n_feat):
        st = out_status[f]
        if not (st == BORDER or st == AMBIGUOUS or st == RUNAWAY or st == FB
                or st == DISAGREES):
            continue
        # its k nearest matches (a handful of features a frame: by brute force)
        near_d[:] = np.inf
        near[:] = 0
        for j in range(c):
            ex = xs[j] - pts[f, 0]
            ey = ys[j] - pts[f, 1]
            d = ex * ex + ey * ey
            if d >= near_d[last]:
                continue
            u = last
            while u > 0 and near_d[u - 1] > d:
                near_d[u] = near_d[u - 1]
                near[u] = near[u - 1]
                u -= 1
            near_d[u] = d
            near[u] = j
        # the displacement the neighbourhood's map gives at the feature's point: the map's
        # linear part (a11, a12; a21, a22) about the neighbours' mean
        a, b, rms = _similarity(xs, ys, dxs, dys, near[:NEIGHBOURS])
        used = NEIGHBOURS
        a11, a12, a21, a22 = a, -b, b, a
        if not rms <= fit:
            if k <= NEIGHBOURS:
                continue  # not one surface (a motion boundary): its motion is not theirs
            for u in range(k):
                fit_pts[0, u] = xs[near[u]]
                fit_pts[1, u] = ys[near[u]]
                fit_pts[2, u] = dxs[near[u]]
                fit_pts[3, u] = dys[near[u]]
            a, b, p, q, rms = _affine(fit_pts)
            if not rms <= fit:
                continue
            used = k
            a11, a12, a21, a22 = a + p, q - b, q + b, a - p
        cx = cy = mx = my = 0.0
        for u in range(used):
            cx += xs[near[u]]
            cy += ys[near[u]]
            mx += dxs[near[u]]
            my += dys[near[u]]
        qx0 = pts[f, 0] - cx / used
        qy0 = pts[f, 1] - cy / used
        mx = mx / used + a11 * qx0 + a12 * qy0
        my = my / used + a21 * qx0 + a22 * qy0
        lim = max(RESCUE_NEAR_PX, 3.0 * rms)
        good, _, x, y = _follow_one(pdata, cdata, geo, pts[f, 0], pts[f, 1], mx, my, n,
                                    scratch)
        if not good:
            continue
        ax = int(np.rint(pts[f, 0]))
        ay = int(np.rint(pts[f, 1]))
        px = pts[f, 0] + (x - ax)
        py = pts[f, 1] + (y - ay)
        if (px - pts[f, 0] - mx) ** 2 + (py - pts[f, 1] - my) ** 2 > lim * lim:
            continue
        if not _returns(prev, curr, pts[f, 0], pts[f, 1], px, py, n, scratch,
                        FOLLOW_FB * fb_bound):
            continue
        if not _keep(pf, cf, w, h, ax, ay, x, y, px, py, n, wts, uniform, f, out_pos, out_ssd):
            continue
        out_status[f] = OK
        count += 1
    return count


@nb.njit(cache=True, nogil=True)
def _back_check(pdata, cdata, geo, pts, back, mirrored, check, n, s, wts, exhaustive, ratio,
                allowance, reject_border, scratch, bound, out_status,
                budget):  # pragma: no cover - numba
    """Step 4 with sub-pixel refinement: the matches ``back`` (in frame t+1) of the features
    at ``pts`` (frame t) tracked back, ``check`` those to check (cleared as each is decided),
    their status set to FB where the way back fails or misses ``pts`` by more than ``bound``
    px. Returns how many are left for the full way back (:func:`_match`, still in ``check``).

    The way back starts as :func:`_match` does (Eq. (1) searched around ``mirrored`` at the
    coarsest level whose pixels hold the template, a failed start starting again a level
    finer, the same tests), but its minimum need only land within a pixel of that level of
    the start: the refinements in between (at most a pixel each) are skipped, and Gauss-Newton
    at the frame's level runs from the start itself. It leaves the start by more than a pixel
    only where the way back misses it by more than ``bound`` (<= 1 px): then, or where it
    cannot run (the window at the image's edge, no texture), the full way back decides.

    A coarse level whose minimum lands more than a pixel from the start counts as failed, as
    one that fails the tests does, and the way back starts again a level finer; only the
    frame's level decides. A coarse level is where a right match's way back goes wrong:
    rotation, zoom and blur between the frames put its integer minimum a pixel or so off, and
    on smooth texture a lookalike several pixels away can be its unique minimum (the way
    there, refined level by level or started again a level finer where its coarse level was
    ambiguous, had found the match). A level finer, the template must still land within one of
    its pixels of the start, searched around the same mirrored prediction with the same tests,
    and Gauss-Newton at the frame's level must bring it within ``bound``: a wrong match passes
    only where frame t holds its template at the start, which is what the check asks. A
    minimum on the search's border is searched again :data:`BACK_MARGIN` px wider: each way's
    window is centred on a whole pixel of its frame, so a match near the edge of the reach one
    way lies up to a pixel beyond it the other."""
    levels = geo.shape[0]
    n_feat = pts.shape[0]
    pending = np.empty(n_feat, np.bool_)
    fine = np.zeros(n_feat, np.bool_)
    anchors = np.empty((n_feat, 2), np.int64)
    centers = np.empty((n_feat, 2), np.int64)
    lq = np.zeros((n_feat, 2), np.int64)
    lssd = np.empty(n_feat, np.float64)
    lstatus = np.empty(n_feat, np.int8)
    # the second search's, for the border minima: one set a call, not one a level
    edge = np.empty(n_feat, np.bool_)
    eq = np.zeros((n_feat, 2), np.int64)
    essd = np.empty(n_feat, np.float64)
    estatus = np.empty(n_feat, np.int8)
    left = 0
    for f in range(n_feat):
        pending[f] = check[f]
        left += check[f]
    for k in range(levels - 1, -1, -1):
        if left == 0:
            break
        scale = 2.0 ** k
        for f in range(n_feat):
            if pending[f]:  # the others' are never read (see _match)
                for c in range(2):
                    anchors[f, c] = int(np.rint(back[f, c] / scale))
                    centers[f, c] = int(np.rint(mirrored[f, c] / scale))
        if _starting(anchors, pending, n, (geo[k, 1], geo[k, 2]), k) == 0:
            continue
        _search_level(_level(cdata, geo, k), _level(pdata, geo, k), anchors, centers, pending,
                      n, s, wts, exhaustive, ratio, allowance * NOISE_GAIN ** k, lq, lssd,
                      lstatus, budget)
        if reject_border:
            # a minimum on the border: searched again a pixel wider (see BACK_MARGIN)
            edges = 0
            for f in range(n_feat):
                edge[f] = pending[f] and lstatus[f] == BORDER
                edges += edge[f]
            if edges:
                _search_level(_level(cdata, geo, k), _level(pdata, geo, k), anchors, centers,
                              edge, n, s + BACK_MARGIN, wts, exhaustive, ratio,
                              allowance * NOISE_GAIN ** k, eq, essd, estatus, budget)
                _take(edge, estatus, essd, eq, lstatus, lssd, lq)
        for f in range(n_feat):
            if not pending[f]:
                continue
            st = lstatus[f]
            if st == OVER:  # not checked: not trusted
                pending[f] = False
                left -= 1
                out_status[f] = OVER
                check[f] = False
                continue
            good = st == OK or (st == BORDER and not reject_border)
            # where the way back lands at level k, against the start there
            ex = (back[f, 0] - pts[f, 0]) / scale + (lq[f, 0] - anchors[f, 0])
            ey = (back[f, 1] - pts[f, 1]) / scale + (lq[f, 1] - anchors[f, 1])
            near = good and abs(ex) <= 1.0 and abs(ey) <= 1.0
            if not near and k > 0:
                continue  # failed here, or landed off the start: starts again a level finer
            pending[f] = False
            left -= 1
            if near:
                fine[f] = True
            else:
                out_status[f] = FB
                check[f] = False
    prev = _level(cdata, geo, 0)
    curr = _level(pdata, geo, 0)
    full = 0
    for f in range(n_feat):
        if not fine[f]:
            continue
        ax = int(np.rint(back[f, 0]))
        ay = int(np.rint(back[f, 1]))
        good, x, y = _refine_with(prev, curr, ax, ay, ax + (pts[f, 0] - back[f, 0]),
                                  ay + (pts[f, 1] - back[f, 1]), n, scratch, NO_THIRD)
        if not good:
            full += 1
            continue
        check[f] = False
        ex = back[f, 0] + (x - ax) - pts[f, 0]
        ey = back[f, 1] + (y - ay) - pts[f, 1]
        if ex * ex + ey * ey > bound * bound:
            out_status[f] = FB
    return full


@nb.njit(cache=True, nogil=True)
def _from_integer(prev, curr, ax, ay, qx, qy, n, wts, uniform, ssd,
                  scratch):  # pragma: no cover - numba
    """The sub-pixel position of the template at (ax, ay) from its integer minimum (qx, qy)
    (S there ``ssd``): Gauss-Newton, or where it cannot run a parabola per axis."""
    good, x, y = _refine_with(prev, curr, ax, ay, float(qx), float(qy), n, scratch, THIRD)
    if good:
        return x, y
    h, w = prev.shape
    ox, oy = _parabola(prev.ravel(), curr.ravel(), w, h, ax, ay, qx, qy, n, wts, uniform, ssd)
    return qx + ox, qy + oy


@nb.njit(cache=True, nogil=True)
def _dominant(pts, pos, status):  # pragma: no cover - numba
    """The frame's dominant motion: the median displacement (dx, dy) of the matches (status
    OK; at least one)."""
    _, _, _, dx, dy = _matches(pts, pos, status)
    return _median_small(dx), _median_small(dy)


@nb.njit(cache=True, nogil=True)
def _dominant_alternative(pdata, cdata, geo, pts, pos, ssd, status, searched, n, wts, uniform,
                          ratio, allowance, bound, apart, arbiter,
                          scratch):  # pragma: no cover - numba
    """Step 5b: a ``searched`` match (not followed: a feature that follows its prediction by
    Gauss-Newton cannot jump a period; its track was tested when it started) whose
    displacement departs from the frame's dominant motion (the median of all the matches')
    by more than ``bound`` px is AMBIGUOUS when the displacement of
    the dominant motion, or one of its 8 neighbours outside the match's own 3x3
    neighbourhood, fits its template about as well: S at most ``ratio`` times the match's
    plus ``allowance``, the uniqueness test's bound. The uniqueness test sees the search
    window of the level the search ran at; on a repetitive texture whose period that level
    aliases (a knit, a grille), a whole patch of features takes the same wrong period, agree
    with each other (no consensus test sees it) and with themselves both ways (nor the
    forward-backward check); the rest of the frame says where else to look.

    Where the scene has depth, the feature's own motion lies away from the frame's, and the
    whole pixels around the frame's miss it: the match is then also followed by Gauss-Newton
    from the dominant motion (:func:`_follow_one`), and where that converges more than
    ``apart`` px from the match, the two minima are compared at their sub-pixel positions
    (:func:`_ssd_bilinear`; at whole pixels a sharp texture's true minimum, 0.4 px away,
    scored 2.5 times the wrong period's), by the same bound, and where the correlation window
    cannot tell them apart, by the wide window of half-width ``arbiter``
    (:func:`_alternative_holds`)."""
    n_feat = pts.shape[0]
    found = 0
    tested = 0  # the searched matches, the only ones tested
    for f in range(n_feat):
        found += status[f] == OK
        tested += status[f] == OK and searched[f]
    if found < MIN_GUIDES or tested == 0:  # (the frame's median costs ~1 us: not for none)
        return
    gx, gy = _dominant(pts, pos, status)
    prev = _level(pdata, geo, 0)
    curr = _level(cdata, geo, 0)
    wide_allowance = _wide_allowance(wts, allowance, arbiter)
    h, w = prev.shape
    pf = prev.ravel()
    cf = curr.ravel()
    for f in range(n_feat):
        if status[f] != OK or not searched[f]:
            continue
        ex = pos[f, 0] - pts[f, 0] - gx
        ey = pos[f, 1] - pts[f, 1] - gy
        if ex * ex + ey * ey <= bound * bound:
            continue
        ax = int(np.rint(pts[f, 0]))
        ay = int(np.rint(pts[f, 1]))
        mx = int(np.rint(pos[f, 0]))
        my = int(np.rint(pos[f, 1]))
        qx = int(np.rint(pts[f, 0] + gx))
        qy = int(np.rint(pts[f, 1] + gy))
        lim = ratio * ssd[f] + allowance
        cap = np.int64(lim) if lim < BIG else BIG
        for y in range(qy - 1, qy + 2):
            for x in range(qx - 1, qx + 2):
                if abs(x - mx) <= 1 and abs(y - my) <= 1:
                    continue
                if x - n < 0 or y - n < 0 or x + n >= w or y + n >= h:
                    continue
                if _ssd_at(pf, cf, w, ax, ay, x, y, n, wts, uniform, cap) <= lim:
                    status[f] = AMBIGUOUS
                    break
            if status[f] != OK:
                break
        if status[f] == OK and apart < np.inf and _alternative_holds(
                pdata, cdata, geo, prev, curr, pts, pos, f, gx, gy, n, wts, ratio, allowance,
                apart, arbiter, wide_allowance, scratch):
            status[f] = AMBIGUOUS


@nb.njit(cache=True, nogil=True)
def _period_alternative(pdata, cdata, geo, pts, pos, status, searched, offset, n, wts, uniform,
                        ratio, allowance, bound, apart, arbiter, reach, scratch,
                        budget):  # pragma: no cover - numba
    """Step 5b, the texture's own period: a ``searched`` match that departs from its
    prediction (``offset``, the predicted displacement) by more than ``bound`` px, on a
    template whose best match in frame t itself within ``reach`` px (outside its 3x3) scores
    at most PERIOD_SELF times ``allowance`` (a texture that repeats: its period v), is
    AMBIGUOUS where Gauss-Newton from the match moved by v or by -v finds another minimum
    about as good (:func:`_alternative_holds`). The frame's dominant motion says where else
    to look only where the feature moves with the frame; a camera that shakes or zooms moves
    the periphery otherwise (a knit matched one period off in RubberWhale's shake and its
    approach, agreeing with its neighbours).

    The self-match is a search of Eq. (1) and draws on the frame's ``budget``
    (:data:`FRAME_WORK`); a match it cannot pay for is not tested. It scores only the
    displacements a bound lets beat the best so far (:func:`_self_match`): on the pipeline's
    built-in frames, whose replay jumps back every 60 frames and tests ~73 features in each
    of the two frames after it, those two frames took 983 / 1245 us, now 656 / 953."""
    prev = _level(pdata, geo, 0)
    curr = _level(cdata, geo, 0)
    wide_allowance = _wide_allowance(wts, allowance, arbiter)
    h, w = prev.shape
    pf = prev.ravel()
    gate = PERIOD_SELF * allowance
    cap0 = np.int64(gate) + 1 if gate < BIG else BIG
    # the self-match's scratch, made at its size for the first match tested (most frames
    # test none)
    rsum, trow, low = _self_match_scratch(0, 0)
    for f in range(pts.shape[0]):
        if status[f] != OK or not searched[f]:
            continue
        ex = pos[f, 0] - pts[f, 0] - offset[f, 0]
        ey = pos[f, 1] - pts[f, 1] - offset[f, 1]
        if ex * ex + ey * ey <= bound * bound:
            continue
        cost = (2 * n + 1) ** 2 * (2 * reach + 1) ** 2
        if budget[0] < cost:
            continue
        budget[0] -= cost
        if low.shape[0] != 2 * reach + 1:
            rsum, trow, low = _self_match_scratch(n, reach)
        best, vx, vy = _self_match(pf, w, h, int(np.rint(pts[f, 0])), int(np.rint(pts[f, 1])),
                                   n, wts, uniform, reach, cap0, rsum, trow, low)
        if best > gate:
            continue  # no period within reach
        mx = pos[f, 0] - pts[f, 0]
        my = pos[f, 1] - pts[f, 1]
        for sign in (-1.0, 1.0):
            if _alternative_holds(pdata, cdata, geo, prev, curr, pts, pos, f, mx + sign * vx,
                                  my + sign * vy, n, wts, ratio, allowance, apart, arbiter,
                                  wide_allowance, scratch):
                status[f] = AMBIGUOUS
                break


@nb.njit(cache=True, nogil=True)
def _self_match_scratch(n, reach):  # pragma: no cover - numba
    """:func:`_self_match`'s scratch for windows of half-width ``n``: (rsum, trow, low)."""
    m = 2 * n + 1
    span = 2 * reach + 1
    return (np.zeros((span + 2 * n, span), np.int64), np.empty(m, np.int64),
            np.zeros((span, span), np.int64))


@nb.njit(**NO_NRT)
def _self_match(pf, w, h, ax, ay, n, wts, uniform, reach, cap, rsum, trow,
                low):  # pragma: no cover - numba
    """The template at (ax, ay) of frame t (flat ``pf``, rows ``w`` long, ``h`` of them)
    matched in frame t itself within ``reach`` px, outside its own 3 x 3: (S, vx, vy) of the
    first minimum in row-major order of (vy, vx) below ``cap``, else (``cap``, 0, 0) (step 5b's
    period, :func:`_period_alternative`). Displacements whose window leaves the frame are
    not scored.

    With uniform weights a displacement is scored only where a bound lets it beat the best
    so far: by Cauchy-Schwarz on each row, m S >= the sum over the rows of (the template's
    row sum - the displaced window's)^2 (``low``), from the row sums of frame t around the
    feature (``rsum``, ``trow``; scratch of :func:`_self_match_scratch`). A displacement
    skipped has S > the best: the same minimum."""
    m = 2 * n + 1
    span = 2 * reach + 1
    if uniform:
        # rsum[r, c]: the m pixels of row ay - reach - n + r from column ax - reach - n + c
        _row_window_sums(pf, w, h, ax - reach - n, ay - reach - n, m, rsum)
        for j in range(m):
            trow[j] = rsum[reach + j, reach]
        # every displacement's bound at once, a row of them a vector (those whose window
        # leaves the frame get any number: they are not scored)
        for r in range(span):
            lr = low[r]
            lr[:] = 0
            for j in range(m):
                t = trow[j]
                rs = rsum[r + j]
                for c in range(span):
                    d = t - rs[c]
                    lr[c] += d * d
    best = cap
    vx = vy = 0
    for dy in range(-reach, reach + 1):
        for dx in range(-reach, reach + 1):
            x = ax + dx
            y = ay + dy
            if ((abs(dx) <= 1 and abs(dy) <= 1) or x - n < 0 or y - n < 0 or x + n >= w
                    or y + n >= h):
                continue
            if uniform and best < BIG and low[dy + reach, dx + reach] > m * best:
                continue  # S > best: it can neither win nor tie
            v = _ssd_at(pf, pf, w, ax, ay, x, y, n, wts, uniform, best)
            if v < best:
                best = v
                vx = dx
                vy = dy
    return best, vx, vy


@nb.njit(**NO_NRT)
def _row_window_sums(pf, w, h, x0, y0, m, out):  # pragma: no cover - numba
    """out[r, c] = the sum of the m pixels of row y0 + r of the frame (flat ``pf``, rows
    ``w`` long, ``h`` of them) from column x0 + c, for every r and c of ``out`` whose pixels
    lie in the frame (a running sum along the row); the others are left as they are."""
    rows, cols = out.shape
    # the columns whose m pixels lie in the frame: x0 + c >= 0 and x0 + c + m <= w
    c_lo = max(0, -x0)
    c_hi = min(cols, w - m - x0 + 1)
    if c_hi <= c_lo:
        return
    for r in range(rows):
        y = y0 + r
        if y < 0 or y >= h:
            continue
        base = y * w + x0
        s = np.int64(0)
        for i in range(m):
            s += np.int64(pf[base + c_lo + i])
        out[r, c_lo] = s
        for c in range(c_lo + 1, c_hi):
            s += np.int64(pf[base + c + m - 1]) - np.int64(pf[base + c - 1])
            out[r, c] = s


@nb.njit(**NO_NRT)
def _alternative_holds(pdata, cdata, geo, prev, curr, pts, pos, f, sx, sy, n, wts, ratio,
                       allowance, apart, arbiter, wide_allowance,
                       scratch):  # pragma: no cover - numba
    """Whether feature f's match ``pos[f]`` has a rival: Gauss-Newton from the displacement
    (sx, sy) (:func:`_follow_one`) converges more than ``apart`` px from it, and the rival's
    S at its sub-pixel position (:func:`_ssd_bilinear`) is at most ``ratio`` times the
    match's plus ``allowance``, the uniqueness test's bound; unless the wide window of
    half-width ``arbiter`` (0: none) scores the rival clearly worse, by the same bound with
    ``wide_allowance`` (:func:`_wide_allowance`)."""
    h, w = prev.shape
    ax = int(np.rint(pts[f, 0]))
    ay = int(np.rint(pts[f, 1]))
    good, _, x, y = _follow_one(pdata, cdata, geo, pts[f, 0], pts[f, 1], sx, sy, n, scratch)
    # the match, as the template centred at (ax, ay) found in frame t+1
    ox = ax + (pos[f, 0] - pts[f, 0])
    oy = ay + (pos[f, 1] - pts[f, 1])
    if (not good or (x - ox) ** 2 + (y - oy) ** 2 <= apart * apart
            or not _bilinear_fits(x, y, n, w, h) or not _bilinear_fits(ox, oy, n, w, h)):
        return False
    if (_ssd_bilinear(prev, curr, ax, ay, x, y, n, wts)
            > ratio * _ssd_bilinear(prev, curr, ax, ay, ox, oy, n, wts) + allowance):
        return False
    if (arbiter <= n or ax - arbiter < 0 or ay - arbiter < 0 or ax + arbiter >= w
            or ay + arbiter >= h or not _bilinear_fits(x, y, arbiter, w, h)
            or not _bilinear_fits(ox, oy, arbiter, w, h)):
        return True
    own = _ssd_bilinear(prev, curr, ax, ay, ox, oy, arbiter, wts)
    rival = _ssd_bilinear(prev, curr, ax, ay, x, y, arbiter, wts)
    return rival <= ratio * own + wide_allowance


@nb.njit(**NO_NRT)
def _wide_allowance(wts, allowance, arbiter):  # pragma: no cover - numba
    """``allowance`` (what noise adds to S over the correlation window's weights ``wts``)
    scaled to the wide window of half-width ``arbiter``, whose pixels weigh one each: once a
    frame, not once a rival."""
    m = 2 * arbiter + 1
    wsum = 0.0
    for j in range(wts.shape[0]):
        for i in range(wts.shape[1]):
            wsum += wts[j, i]
    return allowance * (m * m) / wsum


@nb.njit(**NO_NRT)
def _bilinear_fits(x, y, n, w, h):  # pragma: no cover - numba
    """Whether the (2n+1)^2 window centred at (x, y) and its bilinear samples lie in a w x h
    frame."""
    return x - n >= 0.0 and y - n >= 0.0 and x + n + 1.0 < w and y + n + 1.0 < h


@nb.njit(**NO_NRT)
def _ssd_bilinear(prev, curr, ax, ay, x, y, n, wts):  # pragma: no cover - numba
    """S of Eq. (1) between the (2n+1)^2 template centred at the pixel (ax, ay) of frame t
    (``prev``) and frame t+1 (``curr``) sampled bilinearly at the window centred at (x, y)
    (:func:`_bilinear_fits`), weighted by ``wts`` where it is that window's, else uniform;
    float64 sums (a few matches a frame)."""
    weighted = wts.shape[0] == 2 * n + 1 and wts.shape[1] == 2 * n + 1
    ix = int(np.floor(x))
    iy = int(np.floor(y))
    fx = x - ix
    fy = y - iy
    w00 = (1.0 - fx) * (1.0 - fy)
    w01 = fx * (1.0 - fy)
    w10 = (1.0 - fx) * fy
    w11 = fx * fy
    total = 0.0
    for j in range(-n, n + 1):
        r = iy + j
        for i in range(-n, n + 1):
            c = ix + i
            q = (w00 * float(curr[r, c]) + w01 * float(curr[r, c + 1])
                 + w10 * float(curr[r + 1, c]) + w11 * float(curr[r + 1, c + 1]))
            d = float(prev[ay + j, ax + i]) - q
            total += (wts[j + n, i + n] if weighted else 1.0) * d * d
    return total


@nb.njit(cache=True, nogil=True)
def _consensus(pts, pos, status, bound):  # pragma: no cover - numba
    """Reject (DISAGREES) the matches whose displacement departs from the median displacement
    of their NEIGHBOURS nearest matched features by more than ``bound`` px, or by more than
    three robust standard deviations of those neighbours' own, where they disagree more (a
    motion boundary, several objects). A scene moves alike nearby; a match that moves
    unlike all its neighbours is a lookalike taken for its feature (whose own patch may be
    occluded), which the other tests cannot see when the two match each other both ways.

    The nearest are taken by (squared distance, index), exactly (the medians need only which
    six they are), and the output is the plain all-pairs definition's (the unit test holds it
    to one). Built for speed: on the bench's real frames (~80 matches, 256 x 256) the old
    kernel took ~40 us a frame where its arithmetic needs a few; the time went to mispredicted
    branches (counted with cachegrind: ~3500 a frame). About half went to the insertion sorts
    of the three six-value medians (:func:`.motion._median_small`), now a branch-free min/max
    network (:func:`_middle_of_six`); half to the nearest-neighbour search, which scanned
    outwards in the order of x (~32 matches visited per match, ~15 of them inserted into the
    six kept: x order is not distance order). Here a uniform grid (:func:`_grid`) is searched
    from each match's own 3 x 3 cells outwards (:func:`_ring_runs`): ~22 visited, ~10
    inserted. A brute-force search, tried before, inserts more. Measured old against new
    compiled side by side in one process, on the bench's 7 frame pairs, best of 200 rounds
    of each in turn: 38.5 -> 11.4 us a frame (3.4x); each frame run once in turn with the
    other kernel's (branch predictors untrained on it): 43.0 -> 18.9 us (2.3x).

    Returns the matches it judged (their indices) and their neighbours (:func:`_neighbourhoods`)
    for step 7 (:func:`_reused_neighbourhoods`)."""
    idx, xs, ys, dxs, dys, near = _neighbourhoods(pts, pos, status)
    c = idx.shape[0]
    if c <= NEIGHBOURS:
        return idx, near
    reject = np.zeros(c, np.bool_)
    for a in range(c):
        n0, n1, n2, n3, n4, n5 = near[a, 0], near[a, 1], near[a, 2], near[a, 3], near[a, 4], \
            near[a, 5]
        lo, hi = _middle_of_six(dxs[n0], dxs[n1], dxs[n2], dxs[n3], dxs[n4], dxs[n5])
        mx = 0.5 * (lo + hi)
        lo, hi = _middle_of_six(dys[n0], dys[n1], dys[n2], dys[n3], dys[n4], dys[n5])
        my = 0.5 * (lo + hi)
        # the median of the deviations from their squares (a monotonic map: no square root
        # but for the middle ones)
        lo, hi = _middle_of_six(_dev2(dxs, dys, n0, mx, my), _dev2(dxs, dys, n1, mx, my),
                                _dev2(dxs, dys, n2, mx, my), _dev2(dxs, dys, n3, mx, my),
                                _dev2(dxs, dys, n4, mx, my), _dev2(dxs, dys, n5, mx, my))
        mid = 0.5 * (np.sqrt(lo) + np.sqrt(hi))
        lim = max(bound, 3.0 * 1.4826 * mid)
        reject[a] = _dev2(dxs, dys, a, mx, my) > lim * lim
    for a in range(c):
        if reject[a]:
            status[idx[a]] = DISAGREES
    return idx, near


@nb.njit(cache=True, nogil=True)
def _matches(pts, pos, status):  # pragma: no cover - numba
    """The matches (``status`` OK) of the features at ``pts`` found at ``pos``: their indices,
    and their x, y and displacements dx, dy, as (c,) arrays."""
    n_feat = pts.shape[0]
    idx = np.empty(n_feat, np.int64)
    c = 0
    for f in range(n_feat):
        if status[f] == OK:
            idx[c] = f
            c += 1
    idx = idx[:c]
    xs = np.empty(c, np.float64)
    ys = np.empty(c, np.float64)
    dxs = np.empty(c, np.float64)
    dys = np.empty(c, np.float64)
    for a in range(c):
        f = idx[a]
        xs[a] = pts[f, 0]
        ys[a] = pts[f, 1]
        dxs[a] = pos[f, 0] - pts[f, 0]
        dys[a] = pos[f, 1] - pts[f, 1]
    return idx, xs, ys, dxs, dys


@nb.njit(cache=True, nogil=True)
def _neighbourhoods(pts, pos, status):  # pragma: no cover - numba
    """:func:`_matches`, and each match's NEIGHBOURS nearest (:func:`_nearest`; none where
    there are NEIGHBOURS matches or fewer)."""
    idx, xs, ys, dxs, dys = _matches(pts, pos, status)
    near = (_nearest(xs, ys) if idx.shape[0] > NEIGHBOURS
            else np.empty((0, NEIGHBOURS), np.int64))
    return idx, xs, ys, dxs, dys, near


@nb.njit(cache=True, nogil=True)
def _reused_neighbourhoods(pts, pos, status, judged, judged_near):  # pragma: no cover - numba
    """:func:`_neighbourhoods`, from the neighbourhoods of an earlier set of matches that
    holds this one (``judged``, their indices, and ``judged_near``): the same result. A
    match whose earlier NEIGHBOURS nearest are all still matches has them as its nearest now
    (taking points away brings none nearer), in the same order (by squared distance, then
    index: the indices keep their order); the others (next to a match rejected since: few)
    are searched among the matches. Without an earlier set holding this one, all are searched
    afresh (:func:`_nearest`). Saves step 7 most of the consensus's search."""
    idx, xs, ys, dxs, dys = _matches(pts, pos, status)
    c = idx.shape[0]
    if c <= NEIGHBOURS:
        return idx, xs, ys, dxs, dys, np.empty((0, NEIGHBOURS), np.int64)
    m = judged.shape[0]
    if judged_near.shape[0] != m or m < c:
        return idx, xs, ys, dxs, dys, _nearest(xs, ys)
    # where each earlier match is now (-1: no longer a match); both lists ascend
    now = np.full(m, -1, np.int64)
    a = 0
    for j in range(m):
        if a < c and judged[j] == idx[a]:
            now[j] = a
            a += 1
    if a < c:  # a match the earlier set does not hold
        return idx, xs, ys, dxs, dys, _nearest(xs, ys)
    near = np.empty((c, NEIGHBOURS), np.int64)
    near_d = np.empty(NEIGHBOURS, np.float64)
    last = NEIGHBOURS - 1
    for j in range(m):
        a = now[j]
        if a < 0:
            continue
        kept = True
        for u in range(NEIGHBOURS):
            b = now[judged_near[j, u]]
            if b < 0:
                kept = False
                break
            near[a, u] = b
        if kept:
            continue
        # by (squared distance, index) among the matches, as _nearest keeps them
        near_d[:] = np.inf
        near[a, :] = c
        for b in range(c):
            if b == a:
                continue
            ex = xs[b] - xs[a]
            ey = ys[b] - ys[a]
            d = ex * ex + ey * ey
            if d > near_d[last] or (d == near_d[last] and b > near[a, last]):
                continue
            u = last
            while u > 0 and (near_d[u - 1] > d or (near_d[u - 1] == d and near[a, u - 1] > b)):
                near_d[u] = near_d[u - 1]
                near[a, u] = near[a, u - 1]
                u -= 1
            near_d[u] = d
            near[a, u] = b
    return idx, xs, ys, dxs, dys, near


@nb.njit(cache=True, nogil=True)
def _nearest(xs, ys):  # pragma: no cover - numba
    """Each point's NEIGHBOURS nearest other points (xs, ys), by (squared distance, index),
    sorted by that key: (c, NEIGHBOURS) indices; needs more than NEIGHBOURS points. A
    uniform grid (:func:`_grid`) searched from each point's own 3 x 3 cells outwards
    (:func:`_ring_runs`): see :func:`_consensus` for why."""
    c = xs.shape[0]
    cell, start, sx, sy, si, gw, gh, size = _grid(xs, ys)
    reach2 = (0.999 * size) ** 2  # a cell, less a margin for the rounding of cell indices
    last = NEIGHBOURS - 1
    near_d = np.empty(NEIGHBOURS, np.float64)
    near_i = np.empty(NEIGHBOURS, np.int64)
    runs = np.empty((4 * max(gw, gh) + 3, 2), np.int64)
    near = np.empty((c, NEIGHBOURS), np.int64)
    for a in range(c):
        # the NEIGHBOURS nearest by (squared distance, index), sorted by that key: the 3 x 3
        # cells around a's own, then the square rings of cells farther out, until a ring
        # lies farther than the farthest kept (a point r cells away in x or y lies more than
        # r - 1 cells away). Inline: as a function called per point or per point visited,
        # this loop took 1.5x and 3x as long
        near_d[:] = np.inf
        near_i[:] = c
        xa = xs[a]
        ya = ys[a]
        qx = cell[a] % gw
        qy = cell[a] // gw
        for r in range(1, max(gw, gh) + 1):
            if (r - 1) * (r - 1) * reach2 > near_d[last]:
                break
            for q in range(_ring_runs(r, qx, qy, gw, gh, start, reach2, near_d[last], runs)):
                for t in range(runs[q, 0], runs[q, 1]):
                    b = si[t]
                    if b == a:
                        continue
                    ex = sx[t] - xa
                    ey = sy[t] - ya
                    d = ex * ex + ey * ey
                    if d > near_d[last] or (d == near_d[last] and b > near_i[last]):
                        continue
                    u = last
                    while u > 0 and (near_d[u - 1] > d
                                     or (near_d[u - 1] == d and near_i[u - 1] > b)):
                        near_d[u] = near_d[u - 1]
                        near_i[u] = near_i[u - 1]
                        u -= 1
                    near_d[u] = d
                    near_i[u] = b
        for u in range(NEIGHBOURS):
            near[a, u] = near_i[u]
    return near


#: matches per cell of :func:`_grid`, on average over their bounding box (on the bench's
#: frames 1 to 4 measured within 10 % of each other, 3 the fastest; 6 and 9 slower)
GRID_FILL = 3.0


@nb.njit(cache=True, nogil=True)
def _grid(xs, ys):  # pragma: no cover - numba
    """The points (xs, ys) bucketed in a uniform grid over their bounding box, of square cells
    holding GRID_FILL points on average, at least 1 px wide: each point's cell (row-major
    index), the cells' starts in the points sorted by cell (cell k holds start[k] to
    start[k + 1] - 1), those points' x, y and index, the grid's width and height in cells, and
    the cell size."""
    c = xs.shape[0]
    x0 = xs.min()
    y0 = ys.min()
    w = xs.max() - x0
    h = ys.max() - y0
    # at most about c cells a row or column (points on a line), however thin the box
    size = max(np.sqrt(w * h * GRID_FILL / c), max(w, h) / c, 1.0)
    inv = 1.0 / size
    gw = int(w * inv) + 1
    gh = int(h * inv) + 1
    cell = np.empty(c, np.int64)
    start = np.zeros(gw * gh + 1, np.int64)
    for a in range(c):
        k = int((ys[a] - y0) * inv) * gw + int((xs[a] - x0) * inv)
        cell[a] = k
        start[k + 1] += 1
    for k in range(gw * gh):
        start[k + 1] += start[k]
    fill = start[:-1].copy()
    sx = np.empty(c, np.float64)
    sy = np.empty(c, np.float64)
    si = np.empty(c, np.int64)
    for a in range(c):
        t = fill[cell[a]]
        fill[cell[a]] = t + 1
        sx[t] = xs[a]
        sy[t] = ys[a]
        si[t] = a
    return cell, start, sx, sy, si, gw, gh, size


@nb.njit(**NO_NRT)
def _ring_runs(r, qx, qy, gw, gh, start, reach2, farthest, runs):  # pragma: no cover - numba
    """Into ``runs``: the runs of the grid's sorted points (start, end) of the cells r away
    from cell (qx, qy) (r = 1: the 3 x 3 cells around it, its own row first: the nearest
    first), but for cells that lie farther than ``farthest`` (squared); returns how many."""
    m = 0
    x_lo = max(qx - r, 0)
    x_hi = min(qx + r, gw - 1)
    for oy in range(-r, r + 1):
        cy = qy + oy if r > 1 else qy + (0, -1, 1)[oy + 1]
        if cy < 0 or cy >= gh:
            continue
        row = cy * gw
        if r == 1 or oy == -r or oy == r:  # a whole row of the ring: one run of cells
            runs[m, 0] = start[row + x_lo]
            runs[m, 1] = start[row + x_hi + 1]
            m += 1
            continue
        # the ring's cells left and right in this row, unless farther than the farthest kept
        ky = max(abs(oy) - 1, 0)
        if ((r - 1) * (r - 1) + ky * ky) * reach2 > farthest:
            continue
        for cx in (qx - r, qx + r):
            if 0 <= cx < gw:
                runs[m, 0] = start[row + cx]
                runs[m, 1] = start[row + cx + 1]
                m += 1
    return m


@nb.njit(**NO_NRT)
def _dev2(dxs, dys, n, mx, my):  # pragma: no cover - numba
    """The squared distance of displacement n (dxs[n], dys[n]) from (mx, my)."""
    ex = dxs[n] - mx
    ey = dys[n] - my
    return ex * ex + ey * ey


@nb.njit(**NO_NRT)
def _middle_of_six(v0, v1, v2, v3, v4, v5):  # pragma: no cover - numba
    """The third and fourth smallest of six values (the two that make their median): an
    optimal sorting network (12 compare-exchanges in 5 layers, one a line), branch-free; what
    does not lead to the middle two is dropped by the compiler. NEIGHBOURS is six for this."""
    (v0, v5), (v1, v3), (v2, v4) = _exchange(v0, v5), _exchange(v1, v3), _exchange(v2, v4)
    (v1, v2), (v3, v4) = _exchange(v1, v2), _exchange(v3, v4)
    (v0, v3), (v2, v5) = _exchange(v0, v3), _exchange(v2, v5)
    (v0, v1), (v2, v3), (v4, v5) = _exchange(v0, v1), _exchange(v2, v3), _exchange(v4, v5)
    (v1, v2), (v3, v4) = _exchange(v1, v2), _exchange(v3, v4)
    return v2, v3


@nb.njit(cache=True, nogil=True, inline="always")
def _exchange(a, b):  # pragma: no cover - numba
    """(min, max): a compare-exchange, compiled to a select, not a branch."""
    return min(a, b), max(a, b)


@nb.njit(cache=True, nogil=True)
def _widen(prev, curr, pts, n, wide, acc, ok, out_pos, straddle, even, floor, took,
           cen):  # pragma: no cover - numba
    """The wide window's estimate (:func:`.ssd._refine` over (2 wide + 1)^2, uniform weights)
    from the correlation window's, taken where the wide window's neighbourhood moves as its
    centre does (:func:`_ring_fit`): at the correlation window's estimate, the mean squared
    residual of each side of its ring at most ``straddle`` times its centre's plus ``floor``
    (what noise alone leaves). There more pixels make the estimate more precise, and average
    out the motion blur that changes from frame to frame (it moves the small window's
    estimate and leaves a residual all round). A second motion in the wide window (a surface
    at another depth, a motion boundary) leaves a side that does not fit the centre's motion:
    the correlation window's estimate is kept. Where a side does not fit, the wide estimate
    is still taken where, at that estimate, every side fits about as well as its centre (at
    most ``even`` times its residual plus ``floor``; 0: not tried): strong blur biases the
    small window's estimate, so that the sides fit it worse, but leaves the residual at the
    wide estimate even all round, where a second motion leaves it on a side or two.
    ``straddle`` 0: no test, the wide estimate taken wherever it converges. ``took``: set
    where the wide estimate was taken, and ``cen`` there its window's centroid
    (:func:`.ssd._refine`)."""
    scratch = _refine_scratch(np.ones((2 * wide + 1, 2 * wide + 1), np.int32), acc)
    masks = _ring_masks(n, wide, scratch[0].shape[0])
    for f in range(pts.shape[0]):
        if not ok[f]:
            continue
        ax = int(np.rint(pts[f, 0]))
        ay = int(np.rint(pts[f, 1]))
        x = ax + (out_pos[f, 0] - pts[f, 0])
        y = ay + (out_pos[f, 1] - pts[f, 1])
        good, xw, yw = _refine_with(prev, curr, ax, ay, x, y, wide, scratch, CENTROID)
        if not good:
            continue
        if straddle > 0.0:
            # frames t and t+1 around the window, as the refinement copied them from its
            # start (x, y), which it sampled: the ring's bilinear samples there lie in both
            ix = int(np.floor(x))
            iy = int(np.floor(y))
            inner, ring = _ring_fit(scratch[1], scratch[2], ix, iy, x, y, n, wide, masks)
            if ring > straddle * inner + floor:
                if even <= 0.0:
                    continue
                inner, ring = _ring_fit(scratch[1], scratch[2], ix, iy, xw, yw, n, wide, masks)
                if ring > even * inner + floor:
                    continue
        out_pos[f, 0] = pts[f, 0] + (xw - ax)
        out_pos[f, 1] = pts[f, 1] + (yw - ay)
        took[f] = True
        for k in range(8):
            cen[f, k] = scratch[5][k]


@nb.njit(cache=True, nogil=True)
def _affine_correction(prev, pts, out_pos, status, took, cen, n, wts, uniform, bound,
                       judged, judged_near):  # pragma: no cover - numba
    """Step 7: each match's (``status`` OK) estimate moved from its window's centroids to its
    feature's point, by the scale and rotation of its neighbourhood (or its affine map, where
    it is no similarity), where that is known.

    A translation estimated over a window whose neighbourhood also scales by a and turns by b
    (an approach, a roll: the displacement at its pixel q is t + (a I + b R) q) is, to first
    order, t + (sum H)^-1 sum H (a I + b R) q = t + a c + b c' (H: each pixel's gradient outer
    product; c = (sum H)^-1 sum H q the window's texture-weighted centroid, c' = (sum H)^-1
    sum H R q its turn centroid), not the motion of its centre: with c a few pixels off and a
    10 % scale step, some tenths of a pixel. So the match becomes pos - (a c + b c'), a and b
    the local similarity's, fitted to the displacements of its NEIGHBOURS nearest matches:
    first as they are, then each corrected by the first fit at its own centroids, and taken
    where that fits to within ``bound`` px rms (one surface moving as one; a motion boundary,
    parallax or a non-rigid scene fits worse and is left alone). The window is the wide one
    where :func:`_widen` took its estimate (``took``; its centroids ``cen``, (N, 4): c then
    c', from its Gauss-Newton sums), else the correlation window (``wts``; :func:`_centroid`,
    where the first fit's correction could reach AFFINE_RELEVANT_PX).

    On the scoreboard's approaches (10 % a frame) the median error fell from 0.16 to 0.24 px to
    0.05 to 0.07 (LK 0.27 to 0.33), their drift from 1.5 to 4.1 px to 0.3 to 0.8; the other
    rendered rows and the pairs moved by at most 0.002 px, but Grove2's and Urban2's pairs,
    0.099 -> 0.084 and 0.083 -> 0.078. Tried first outside the tracker: the true scale and
    rotation gave about what the fitted ones give; one similarity fitted to the whole frame
    made the pairs worse (Urban2's 0.084 -> 0.129: parallax is not a similarity), and so did
    the local fits taken everywhere (0.120); the second fit's residual is the test that tells
    them apart. The turn was first corrected by b R c, as if c' were R c (true only where the
    window's texture has no direction): on the scoreboard's roll (3 degrees a frame) that left
    the median error at 0.16 to 0.21 px, LK's; with c', 0.026 to 0.031 (the pairs: Grove2's
    0.084 -> 0.095, Urban2's 0.078 -> 0.075, with up to 500 features 0.080 -> 0.077 and 0.079
    -> 0.078). Where the neighbourhood is no similarity (a plane in perspective: its scale
    along x and y apart) and AFFINE_GENERAL, an affine map [[a + p, s - b], [s + b, a - p]]
    is fitted the same way (the neighbours corrected by the first fit at their own
    centroids, then fitted again) and taken where it fits to within AFFINE_GENERAL_FIT of
    ``bound``: the estimate moves by a c + b c' + p d + s e, d and e the window's stretch and
    shear centroids (sum H)^-1 sum H (i, -j) and (sum H)^-1 sum H (j, i) (``cen``'s last
    four). Forward driving over a plane, 12 frames, up to 35 px a frame: medians 0.082 to
    0.135 -> 0.043 to 0.105 px (LK 0.18 to 0.40); the pairs' Venus 0.171 -> 0.157, Urban2
    0.075 -> 0.058, Grove2 0.095 -> 0.101 (with up to 500 features: 0.185 -> 0.183, 0.078 ->
    0.072, 0.077 unchanged). The neighbours are the consensus's (``judged``,
    ``judged_near``; empty when it did not run), where they are all still matches
    (:func:`_reused_neighbourhoods`)."""
    idx, xs, ys, dxs, dys, near = _reused_neighbourhoods(pts, out_pos, status, judged,
                                                         judged_near)
    c = idx.shape[0]
    if c <= NEIGHBOURS:
        return
    # the first fit, and the centroids where its correction can matter: (c, c', d, e) a
    # match, the centroids of its window's scale, turn, stretch and shear (8 numbers)
    sa = np.empty(c, np.float64)
    sb = np.empty(c, np.float64)
    cq = np.zeros((c, 8), np.float64)
    have = np.zeros(c, np.bool_)
    cs = _centroid_scratch(wts, uniform)
    for a in range(c):
        sa[a], sb[a], _ = _similarity_of(xs, ys, dxs, dys, near, a)
        if (took[idx[a]] or (abs(sa[a]) + abs(sb[a])) * n >= AFFINE_RELEVANT_PX):
            _centroids_of(prev, pts, took, cen, idx, n, wts, uniform, a, cq, have, cs)
    ex = np.empty(c, np.float64)
    ey = np.empty(c, np.float64)
    for a in range(c):
        ex[a] = dxs[a] - (sa[a] * cq[a, 0] + sb[a] * cq[a, 2])
        ey[a] = dys[a] - (sa[a] * cq[a, 1] + sb[a] * cq[a, 3])
    fit = np.empty((4, NEIGHBOURS), np.float64)
    for a in range(c):
        if not have[a]:
            continue
        ka, kb, rms = _similarity_of(xs, ys, ex, ey, near, a)
        f = idx[a]
        if rms <= bound and ka * ka + kb * kb <= AFFINE_MAX * AFFINE_MAX:
            out_pos[f, 0] -= ka * cq[a, 0] + kb * cq[a, 2]
            out_pos[f, 1] -= ka * cq[a, 1] + kb * cq[a, 3]
        elif AFFINE_GENERAL:
            # no similarity: an affine neighbourhood (a plane seen in perspective, its scale
            # along x and y apart) is fitted, its neighbours corrected by that fit at their
            # own centroids, fitted again
            for u in range(NEIGHBOURS):
                j = near[a, u]
                if not have[j]:
                    _centroids_of(prev, pts, took, cen, idx, n, wts, uniform, j, cq, have, cs)
                fit[0, u] = xs[j]
                fit[1, u] = ys[j]
                fit[2, u] = dxs[j]
                fit[3, u] = dys[j]
            a1, b1, p1, s1, rms1 = _affine(fit)
            if not rms1 < np.inf:
                continue
            for u in range(NEIGHBOURS):
                j = near[a, u]
                fit[2, u] = dxs[j] - (a1 * cq[j, 0] + b1 * cq[j, 2] + p1 * cq[j, 4]
                                      + s1 * cq[j, 6])
                fit[3, u] = dys[j] - (a1 * cq[j, 1] + b1 * cq[j, 3] + p1 * cq[j, 5]
                                      + s1 * cq[j, 7])
            a2, b2, p2, s2, rms2 = _affine(fit)
            if (rms2 <= AFFINE_GENERAL_FIT * bound
                    and a2 * a2 + b2 * b2 + p2 * p2 + s2 * s2 <= AFFINE_MAX ** 2):
                out_pos[f, 0] -= (a2 * cq[a, 0] + b2 * cq[a, 2] + p2 * cq[a, 4]
                                  + s2 * cq[a, 6])
                out_pos[f, 1] -= (a2 * cq[a, 1] + b2 * cq[a, 3] + p2 * cq[a, 5]
                                  + s2 * cq[a, 7])


@nb.njit(**NO_NRT)
def _centroids_of(prev, pts, took, cen, idx, n, wts, uniform, a, cq, have,
                  cs):  # pragma: no cover - numba
    """Match a's centroids into ``cq[a]`` (the wide window's where it was taken, else the
    correlation window's, :func:`_centroid_fast`, its scratch ``cs``), ``have[a]`` set."""
    f = idx[a]
    if took[f]:
        for k in range(8):
            cq[a, k] = cen[f, k]
    else:
        (cq[a, 0], cq[a, 1], cq[a, 2], cq[a, 3], cq[a, 4], cq[a, 5], cq[a, 6],
         cq[a, 7]) = _centroid_fast(prev, int(np.rint(pts[f, 0])), int(np.rint(pts[f, 1])), n,
                                    wts, uniform, cs[0], cs[1], cs[2], cs[3])
    have[a] = True


@nb.njit(**NO_NRT)
def _affine(fit):  # pragma: no cover - numba
    """The least-squares affine map of the displacements fit[2:4] of the points fit[0:2]
    (k of them: NEIGHBOURS, or step 5c's RESCUE_AFFINE_NEAR), its matrix less the identity
    split into scale a, turn b, stretch p and shear s ([[a + p, s - b], [s + b, a - p]]), and
    the rms of its residuals over the 2 k coordinates: (a, b, p, s, rms); rms infinite where
    the points lie on a line."""
    k = fit.shape[1]
    mx = my = mu = mv = 0.0
    for u in range(k):
        mx += fit[0, u]
        my += fit[1, u]
        mu += fit[2, u]
        mv += fit[3, u]
    mx /= k
    my /= k
    mu /= k
    mv /= k
    sxx = sxy = syy = sxu = syu = sxv = syv = 0.0
    for u in range(k):
        x = fit[0, u] - mx
        y = fit[1, u] - my
        du = fit[2, u] - mu
        dv = fit[3, u] - mv
        sxx += x * x
        sxy += x * y
        syy += y * y
        sxu += x * du
        syu += y * du
        sxv += x * dv
        syv += y * dv
    det = sxx * syy - sxy * sxy
    if det <= 1e-6 * (sxx + syy) * (sxx + syy) or det <= 0.0:
        return 0.0, 0.0, 0.0, 0.0, np.inf
    a11 = (syy * sxu - sxy * syu) / det
    a12 = (sxx * syu - sxy * sxu) / det
    a21 = (syy * sxv - sxy * syv) / det
    a22 = (sxx * syv - sxy * sxv) / det
    r2 = 0.0
    for u in range(k):
        x = fit[0, u] - mx
        y = fit[1, u] - my
        ru = fit[2, u] - mu - (a11 * x + a12 * y)
        rv = fit[3, u] - mv - (a21 * x + a22 * y)
        r2 += ru * ru + rv * rv
    return ((a11 + a22) / 2.0, (a21 - a12) / 2.0, (a11 - a22) / 2.0, (a12 + a21) / 2.0,
            np.sqrt(r2 / (2 * k)))


@nb.njit(**NO_NRT)
def _similarity_of(xs, ys, dxs, dys, near, a):  # pragma: no cover - numba
    """:func:`_similarity` of the points ``near[a]``: the row's view made here, without
    numba's reference counts (an atomic increment and decrement a view where it runs)."""
    return _similarity(xs, ys, dxs, dys, near[a])


@nb.njit(**NO_NRT)
def _similarity(xs, ys, dxs, dys, near):  # pragma: no cover - numba
    """The least-squares similarity of the displacements (dxs, dys) of the points ``near``:
    d = t + a (p - m) + b R (p - m), R the quarter turn, m their mean: NEIGHBOURS of them, a
    constant, so that LLVM unrolls the loops (77 -> 68 ns a call on the bench's frames, the
    same floats). Returns (a, b, the rms of its residuals over the 2 k coordinates); (0, 0,
    inf) where the points coincide."""
    k = NEIGHBOURS
    mx = my = mu = mv = 0.0
    for u in range(NEIGHBOURS):
        j = near[u]
        mx += xs[j]
        my += ys[j]
        mu += dxs[j]
        mv += dys[j]
    mx /= k
    my /= k
    mu /= k
    mv /= k
    sxx = sa = sb = 0.0
    for u in range(NEIGHBOURS):
        j = near[u]
        x = xs[j] - mx
        y = ys[j] - my
        du = dxs[j] - mu
        dv = dys[j] - mv
        sxx += x * x + y * y
        sa += x * du + y * dv
        sb += x * dv - y * du
    if sxx <= 1e-9:
        return 0.0, 0.0, np.inf
    a = sa / sxx
    b = sb / sxx
    r2 = 0.0
    for u in range(NEIGHBOURS):
        j = near[u]
        x = xs[j] - mx
        y = ys[j] - my
        ru = dxs[j] - mu - (a * x - b * y)
        rv = dys[j] - mv - (b * x + a * y)
        r2 += ru * ru + rv * rv
    return a, b, np.sqrt(r2 / (2 * k))


@nb.njit(**NO_NRT)
def _centroid(img, ax, ay, half, wts, uniform):  # pragma: no cover - numba
    """The texture-weighted centroid (cx, cy) of the (2 half + 1)^2 window at (ax, ay) of
    ``img``, relative to its centre, (sum W H)^-1 sum W H q, H the outer product of the
    central-difference gradient at pixel q, W ``wts`` (or 1 where ``uniform``), and its turn
    centroid (rx, ry) = (sum W H)^-1 sum W H R q, R q = (-j, i): a translation estimated over
    the window whose neighbourhood scales by a and turns by b measures, to first order, the
    motion at a (cx, cy) + b (rx, ry). (cx, cy, rx, ry); zeros where the window (and its 1 px
    margin) leaves the image or has no texture. Integer sums."""
    h, w = img.shape
    if ax - half - 1 < 0 or ay - half - 1 < 0 or ax + half + 1 >= w or ay + half + 1 >= h:
        return 0.0, 0.0, 0.0, 0.0, 0.0, 0.0, 0.0, 0.0
    hxx = hxy = hyy = vx = vy = wx = wy = sdx = sdy = shx = shy = 0
    for j in range(-half, half + 1):
        up = img[ay + j - 1]
        row = img[ay + j]
        down = img[ay + j + 1]
        for i in range(-half, half + 1):
            x = ax + i
            gx = np.int64(row[x + 1]) - np.int64(row[x - 1])
            gy = np.int64(down[x]) - np.int64(up[x])
            wq = 1 if uniform else np.int64(wts[j + half, i + half])
            gxx = wq * gx * gx
            gxy = wq * gx * gy
            gyy = wq * gy * gy
            hxx += gxx
            hxy += gxy
            hyy += gyy
            vx += gxx * i + gxy * j
            vy += gxy * i + gyy * j
            wx += gxy * i - gxx * j
            wy += gyy * i - gxy * j
            sdx += gxx * i - gxy * j
            sdy += gxy * i - gyy * j
            shx += gxx * j + gxy * i
            shy += gxy * j + gyy * i
    return _centroids_from(hxx, hxy, hyy, vx, vy, wx, wy, sdx, sdy, shx, shy)


@nb.njit(**NO_NRT)
def _centroids_from(hxx, hxy, hyy, vx, vy, wx, wy, sdx, sdy, shx, shy):  # pragma: no cover
    """:func:`_centroid`'s eight centroids from its integer sums (int64)."""
    det = float(hxx) * float(hyy) - float(hxy) * float(hxy)
    if det <= 1e-6 * float(hxx + hyy) * float(hxx + hyy) or det <= 0.0:
        return 0.0, 0.0, 0.0, 0.0, 0.0, 0.0, 0.0, 0.0
    return ((float(hyy) * vx - float(hxy) * vy) / det,
            (float(hxx) * vy - float(hxy) * vx) / det,
            (float(hyy) * wx - float(hxy) * wy) / det,
            (float(hxx) * wy - float(hxy) * wx) / det,
            (float(hyy) * sdx - float(hxy) * sdy) / det,
            (float(hxx) * sdy - float(hxy) * sdx) / det,
            (float(hyy) * shx - float(hxy) * shy) / det,
            (float(hxx) * shy - float(hxy) * shx) / det)


@nb.njit(cache=True, nogil=True)
def _centroid_scratch(wts, uniform):  # pragma: no cover - numba
    """:func:`_centroid_fast`'s scratch for the window of weights ``wts`` (or 1 where
    ``uniform``): (patch, weights, i, j), the window's pixel (j, i) at lane j (m + 2) + i (its
    weight, and its i and j from the centre), zero on the lanes between rows; the weights
    empty where the sums could outgrow int32 (then summed as :func:`_centroid` does)."""
    m = wts.shape[0]
    half = m // 2
    s = m + 2
    lanes = (m - 1) * s + m
    patch = np.zeros(s * s + LANES, np.uint8)  # whole vectors of LANES (.ssd._patch)
    wq = np.zeros(lanes, np.int32)
    qi = np.zeros(lanes, np.int32)
    qj = np.zeros(lanes, np.int32)
    bound = 0.0  # the largest any sum can be: 255^2 |W| (|i| + |j|), or 255^2 |W|
    for j in range(m):
        for i in range(m):
            wt = 1 if uniform else wts[j, i]
            wq[j * s + i] = wt
            qi[j * s + i] = i - half
            qj[j * s + i] = j - half
            bound += 255.0 * 255.0 * abs(wt) * max(abs(i - half) + abs(j - half), 1)
    if bound >= 2.0**31:
        wq = wq[:0]
    return patch, wq, qi, qj


@nb.njit(**NO_NRT)
def _centroid_fast(img, ax, ay, half, wts, uniform, patch, wq, qi, qj):  # pragma: no cover
    """:func:`_centroid`, the same sums (exact integers) in int32 over the lanes of a patch
    of ``img`` (``patch``, ``wq``, ``qi``, ``qj``: :func:`_centroid_scratch`; where its
    weights are empty, :func:`_centroid` itself), which LLVM vectorises: on the bench's
    frames 446 -> 197 ns a 9 x 9 window (int64 a pixel at a time before), the same
    outputs."""
    h, w = img.shape
    if ax - half - 1 < 0 or ay - half - 1 < 0 or ax + half + 1 >= w or ay + half + 1 >= h:
        return 0.0, 0.0, 0.0, 0.0, 0.0, 0.0, 0.0, 0.0
    if wq.shape[0] == 0:
        return _centroid(img, ax, ay, half, wts, uniform)
    s = 2 * half + 3
    _patch(img, ax - half - 1, ay - half - 1, s, s, patch, s)
    # the window's pixel at lane q is patch[q + s + 1]; its neighbours around it (offsets in
    # slices, the index the loop's own: see .ssd._refine). numba types int32 * int32 as int64:
    # the casts keep the arithmetic in int32, which LLVM then narrows
    right = patch[s + 2:]
    left = patch[s:]
    down = patch[2 * s + 1:]
    up = patch[1:]
    i32 = np.int32
    hxx = hxy = hyy = vx = vy = wx = wy = sdx = sdy = shx = shy = i32(0)
    for q in range(wq.shape[0]):
        gx = i32(i32(right[q]) - i32(left[q]))
        gy = i32(i32(down[q]) - i32(up[q]))
        wt = wq[q]
        gxx = i32(wt * i32(gx * gx))
        gxy = i32(wt * i32(gx * gy))
        gyy = i32(wt * i32(gy * gy))
        i = qi[q]
        j = qj[q]
        hxx = i32(hxx + gxx)
        hxy = i32(hxy + gxy)
        hyy = i32(hyy + gyy)
        vx = i32(vx + i32(i32(gxx * i) + i32(gxy * j)))
        vy = i32(vy + i32(i32(gxy * i) + i32(gyy * j)))
        wx = i32(wx + i32(i32(gxy * i) - i32(gxx * j)))
        wy = i32(wy + i32(i32(gyy * i) - i32(gxy * j)))
        sdx = i32(sdx + i32(i32(gxx * i) - i32(gxy * j)))
        sdy = i32(sdy + i32(i32(gxy * i) - i32(gyy * j)))
        shx = i32(shx + i32(i32(gxx * j) + i32(gxy * i)))
        shy = i32(shy + i32(i32(gxy * j) + i32(gyy * i)))
    return _centroids_from(np.int64(hxx), np.int64(hxy), np.int64(hyy), np.int64(vx),
                           np.int64(vy), np.int64(wx), np.int64(wy), np.int64(sdx),
                           np.int64(sdy), np.int64(shx), np.int64(shy))


@nb.njit(cache=True, nogil=True)
def _ring_masks(n, wide, size):  # pragma: no cover - numba
    """(RING_MASKS, size) int16: -1 on the lanes of the wide window's pixels left of the
    centre's columns, right of them, and in them above, within and below the centre's rows
    (pixel (j, i) of the window at lane j * (2 wide + 5) + i, the layout of
    :func:`.ssd._refine`'s patches), 0 elsewhere (the lanes between rows and after the
    window): what :func:`_ring_fit` sums by."""
    stride = 2 * wide + 5
    masks = np.zeros((RING_MASKS, size), np.int16)
    for j in range(2 * wide + 1):
        for i in range(2 * wide + 1):
            if i < wide - n:
                k = 0
            elif i > wide + n:
                k = 1
            else:
                k = 2 if j < wide - n else 4 if j > wide + n else 3
            masks[k, j * stride + i] = -1
    return masks


@nb.njit(**NO_NRT)
def _ring_fit(tp, cp, ix, iy, x, y, n, wide, masks):  # pragma: no cover - numba
    """Mean squared residuals of the template of frame t, (2 wide + 1)^2, against frame t+1
    sampled bilinearly at (x, y): over its central (2 n + 1)^2, and the largest of those over
    the four sides of the ring around it (left and right: the full height; above and below:
    the centre's width). A second motion in the window leaves its residual on a side or two,
    blur all round. The frames are read from the patches of the wide window's Gauss-Newton
    refinement (:func:`.ssd._refine`: ``tp`` frame t around the template, ``cp`` frame t+1
    around its start, whose whole pixel is (ix, iy)), which converged: (x, y) is that start,
    or where it converged, within a pixel of it; the window and its bilinear samples lie
    inside both patches (and both frames). ``masks``: :func:`_ring_masks`.

    The residuals in 1/BILINEAR_ONE grey levels, their squares summed exactly in integers
    (the same on every machine), as 16-bit multiply-adds (:func:`.ssd._masked_squares`):
    138 to 153 ns a 21 px window, where numba's loop over the same lanes took 353 to 360."""
    stride = 2 * wide + 5
    bx = int(np.floor(x))
    by = int(np.floor(y))
    fx = x - bx
    fy = y - by
    # the bilinear weights in 1/BILINEAR_ONE, summing to it exactly
    w01 = np.int16(np.rint(fx * (1.0 - fy) * BILINEAR_ONE))
    w10 = np.int16(np.rint((1.0 - fx) * fy * BILINEAR_ONE))
    w11 = np.int16(np.rint(fx * fy * BILINEAR_ONE))
    w00 = np.int16(BILINEAR_ONE - w01 - w10 - w11)
    # the window's pixel (j, i), 0 to 2 wide, at lane j * stride + i: the template's at
    # tp[t0 + lane] (its patch has a 2 px margin), frame t+1's (by - wide + j, bx - wide + i)
    # at cp[c0 + lane] (its patch starts a pixel before (ix - wide, iy - wide)); the lanes up
    # to the window's last pixel, in whole steps of 2 DOT_LANES (the masks zero after it;
    # within the patches' and masks' length, a multiple of ssd.VEC, 128)
    t0 = 2 * stride + 2
    c0 = (by - iy + 1) * stride + (bx - ix + 1)
    step = 2 * DOT_LANES
    used = (2 * wide * stride + 2 * wide + 1 + step - 1) // step * step
    left, right, top, inner, bottom = _masked_squares(tp, t0, cp, c0, stride,
                                                      (w00, w01, w10, w11), masks, used)
    m = 2 * n + 1
    side = float(2 * wide + 1) * (wide - n) * BILINEAR_ONE * BILINEAR_ONE
    cap = float(m) * (wide - n) * BILINEAR_ONE * BILINEAR_ONE
    return (inner / (float(m * m) * BILINEAR_ONE * BILINEAR_ONE),
            max(left / side, right / side, top / cap, bottom / cap))


@nb.njit(cache=True, nogil=True)
def _ring_fit_at(prev, curr, ax, ay, x, y, n, wide):  # pragma: no cover - numba
    """:func:`_ring_fit` from the frames: the patches copied here as the wide window's
    refinement copies them, from Gauss-Newton's start (x, y) (a test's)."""
    m = 2 * wide + 1
    wpad, tp, cp, _, _, _, _ = _refine_scratch(np.ones((m, m), np.int32),
                                               np.empty(0, np.int32))
    ix = int(np.floor(x))
    iy = int(np.floor(y))
    _patch(prev, ax - wide - 2, ay - wide - 2, m + 4, m + 4, tp, m + 4)
    _patch(curr, ix - wide - 1, iy - wide - 1, m + 3, m + 3, cp, m + 4)
    return _ring_fit(tp, cp, ix, iy, x, y, n, wide, _ring_masks(n, wide, wpad.shape[0]))


class WideTests(TypedDict):
    """:func:`wide_tests`' keyword arguments of :func:`track_pyramid`."""

    straddle: float
    even: float
    floor: float


def wide_tests(noise: float) -> WideTests:
    """:func:`track_pyramid`'s ``straddle``, ``even`` and ``floor`` (the wide window's tests,
    step 6 of the module notes) for a camera noise of ``noise`` grey levels."""
    return {"straddle": STRADDLE, "even": EVEN, "floor": 2.0 * noise * noise}


@functools.lru_cache(maxsize=16)
def _sum_type(weights: bytes, corr_half: int, wide_half: int) -> np.ndarray:
    """The sub-pixel sums' type (:func:`.ssd.refine_acc`) for the correlation window of
    ``weights`` (int32 W, the bytes of a (2 corr_half + 1)^2 array) and the wide window of
    ``wide_half`` (-1: no sub-pixel refinement, so none is summed: int32, the kernels' one
    specialisation). Kept per window: it took ~7 us a frame, 1 % of the default tracker."""
    if wide_half < 0:
        return np.empty(0, np.int32)
    m = 2 * corr_half + 1
    wts = np.frombuffer(weights, np.int32).reshape(m, m)
    if wide_half > corr_half:
        return refine_acc(wts, np.ones((2 * wide_half + 1,) * 2, np.int32))
    return refine_acc(wts)


def sum_type(weights: np.ndarray, corr_half: int, wide_half: int) -> str:
    """The name of the integer type (int32 or int64) in which :func:`track_pyramid` sums the
    sub-pixel refinement for the correlation window of ``weights`` (int32, (2 corr_half + 1)^2)
    and the wide window of ``wide_half`` (-1: no sub-pixel refinement). The kernels compile
    for each type once: int64 (the largest windows) is a set of its own."""
    return _sum_type(weights.tobytes(), int(corr_half), int(wide_half)).dtype.name


def track_pyramid(prev: Pyramid, curr: Pyramid, points: np.ndarray, predictions: np.ndarray,
                  *, corr_half: int, search_half: int, weights: np.ndarray,
                  subpixel: bool = False, search: str = "pruned", uniqueness: float = 0.0,
                  allowance: float = 0.0, reject_border: bool = False,
                  guided_retry: bool = False, max_fb_error: float = 0.0,
                  consensus: float = 0.0, wide_half: int = 0,
                  straddle: float = 0.0, even: float = 0.0, floor: float = 0.0,
                  held: np.ndarray | None = None, follow: bool = False,
                  followed: np.ndarray | None = None, work: int = FRAME_WORK
                  ) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Track features from frame t to frame t+1 coarse to fine (see the module notes).

    Parameters
    ----------
    prev, curr : the pyramids of frames t and t+1 (:func:`build_pyramid`, same levels).
    points : (N, 2) float x, y of the features in frame t, px (sub-pixel).
    predictions : (N, 2) float x, y where each is expected in frame t+1, px.
    corr_half, search_half, weights : n, SEARCH_SIZE // 2 and W(i, j) of Eq. (1), as in
        :func:`.ssd.track_ssd`; the search half-width is in pixels of the start level.
    subpixel : refine the matches to sub-pixel positions (:func:`.ssd._subpixel`).
    search : ``"pruned"`` or ``"exhaustive"``, how the starts find their argmin.
    uniqueness : a start fails when a displacement outside its minimum's 3x3 neighbourhood
        has S <= uniqueness * S_min + allowance; 0 turns the test off.
    allowance : what noise alone adds to S at a perfect match (2 sigma^2 sum W).
    reject_border : a start fails when its minimum lies on the search window's border.
    guided_retry : search the features that found no trustworthy minimum again around the
        frame's dominant motion.
    max_fb_error : the forward-backward bound, px; 0 turns the check off.
    consensus : a match whose displacement departs from its nearest neighbours' by more than
        this, px, is rejected (see :func:`_consensus`); 0 turns the check off.
    wide_half : half-width of the wide sub-pixel window (0: the correlation window only).
    straddle, even, floor : the wide window's estimate is taken where, at the correlation
        window's estimate, the mean squared residual of each side of its ring is at most
        ``straddle`` times that of its centre plus ``floor`` (grey levels^2), or else, at the
        wide estimate, at most ``even`` times its centre's plus ``floor`` (see :func:`_widen`);
        ``straddle`` 0: wherever it converges; ``even`` 0: no second test.
    held : (N,) bool, the features to follow first (step 0; the tracker: all); None: none.
    follow : follow the held features from their prediction by Gauss-Newton first (step 0 of
        the module notes); needs ``subpixel`` and ``max_fb_error`` > 0.
    followed : (N,) bool, set where the feature was taken by step 0 (the others were searched
        coarse to fine; the consensus may still reject it); None: not wanted.
    work : the searches of Eq. (1) this call may make, window pixels x displacements, over
        every level and step (:data:`FRAME_WORK`); a feature whose search would exceed what
        is left is not searched (status :data:`.ssd.OVER`).

    Returns
    -------
    pos : (N, 2) float64 positions in frame t+1, NaN where not found;
    ssd : (N,) float64 S of Eq. (1) at the integer match of the frame's level (inf where not
        found);
    status : (N,) int8, :data:`.ssd.OK` or why the feature was not found
        (:data:`.ssd.STATUS_NAMES`).
    """
    plan = TrackPlan(corr_half=corr_half, search_half=search_half, weights=weights,
                     subpixel=subpixel, search=search, uniqueness=uniqueness,
                     allowance=allowance, reject_border=reject_border,
                     guided_retry=guided_retry, max_fb_error=max_fb_error, consensus=consensus,
                     wide_half=wide_half, straddle=straddle, even=even, floor=floor,
                     follow=follow)
    return plan.track(prev, curr, points, predictions, held=held, followed=followed, work=work)


class TrackPlan:
    """:func:`track_pyramid`'s settings, checked and converted once for a run of frames: a
    tracker makes one when its parameters or its noise estimate change and tracks each frame
    pair with :meth:`track`. Checking and converting ~30 settings every call took 3 to 4 us
    of a frame pair: on the bench's held frames track_pyramid 117.0 to 118.1 us a pair,
    plan.track 114.3 to 115.0 (one process, interleaved, best of 100 rounds, 4 rounds)."""

    __slots__ = ("_settings", "_guided_retry", "_search_half", "_follow")

    def __init__(self, *, corr_half: int, search_half: int, weights: np.ndarray,
                 subpixel: bool = False, search: str = "pruned", uniqueness: float = 0.0,
                 allowance: float = 0.0, reject_border: bool = False,
                 guided_retry: bool = False, max_fb_error: float = 0.0,
                 consensus: float = 0.0, wide_half: int = 0,
                 straddle: float = 0.0, even: float = 0.0, floor: float = 0.0,
                 follow: bool = False) -> None:
        if search not in SEARCH_KINDS:
            raise ValueError(f"search={search!r} is not allowed: use one of "
                             f"{', '.join(SEARCH_KINDS)}")
        m = 2 * corr_half + 1
        if weights.shape != (m, m):
            raise ValueError(f"weights of shape {weights.shape} do not match "
                             f"corr_half={corr_half}")
        wts = np.ascontiguousarray(weights, np.int32)
        acc = _sum_type(wts.tobytes(), int(corr_half), int(wide_half) if subpixel else -1)
        # the kernel's arguments from corr_half to floor, in its order (_track_frame)
        self._settings = (
            int(corr_half), int(search_half), wts, search == "exhaustive", float(uniqueness),
            float(allowance), bool(reject_border), bool(guided_retry), float(max_fb_error),
            float(consensus), float(DOMINANT_PX), float(DOMINANT_FOLLOW_PX),
            int(PERIOD_REACH), float(PERIOD_DEPART_PX),
            int(wide_half) if WIDE_ARBITER and subpixel else 0, float(AFFINE_FIT_PX),
            float(RESCUE_FIT_PX), int(RESCUE_AFFINE_NEAR), bool(subpixel), int(wide_half), acc,
            float(straddle), float(even), float(floor))
        self._guided_retry = bool(guided_retry)
        self._search_half = float(search_half)
        self._follow = bool(follow)

    def track(self, prev: Pyramid, curr: Pyramid, points: np.ndarray, predictions: np.ndarray,
              *, held: np.ndarray | None = None, followed: np.ndarray | None = None,
              work: int = FRAME_WORK, budget: np.ndarray | None = None
              ) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """Track ``points`` of frame t (``prev``) into frame t+1 (``curr``) from
        ``predictions``: :func:`track_pyramid` with these settings. ``budget``: a (1,) int64
        array of what is left of the searches' work, drawn on in place, for a frame whose
        searches take several calls (the tracker's zoom retry); default a new one of
        ``work``."""
        if prev.shapes != curr.shapes:
            raise ValueError(f"pyramids of different shapes: {prev.shapes} and {curr.shapes}")
        pts = np.ascontiguousarray(points, np.float64).reshape(-1, 2)
        preds = np.ascontiguousarray(predictions, np.float64).reshape(-1, 2)
        if pts.shape != preds.shape:
            raise ValueError(f"points {pts.shape} and predictions {preds.shape} differ in "
                             "shape")
        if budget is None:
            if not 0 <= work <= NO_BUDGET:
                raise ValueError(f"work must be 0 to {NO_BUDGET}: got {work}")
            budget = np.array((work,), np.int64)  # one C call (np.full is two, in Python)
        elif budget.shape != (1,) or budget.dtype != np.int64 or not 0 <= budget[0] <= NO_BUDGET:
            raise ValueError(f"budget must be a (1,) int64 array of 0 to {NO_BUDGET}")
        n_feat = len(pts)
        pos = np.empty((n_feat, 2), np.float64)
        ssd = np.empty(n_feat, np.float64)
        status = np.empty(n_feat, np.int8)
        hold = (np.zeros(n_feat, np.bool_) if held is None
                else np.ascontiguousarray(held, np.bool_).reshape(-1))
        if hold.shape[0] != n_feat:
            raise ValueError(f"held has {hold.shape[0]} entries for {n_feat} points")
        taken = np.zeros(n_feat, np.bool_) if followed is None else followed
        if taken.shape != (n_feat,) or taken.dtype != np.bool_:
            raise ValueError(f"followed must be a ({n_feat},) bool array")
        settings = self._settings

        def run(preds: np.ndarray, hold: np.ndarray, follow: bool, pos: np.ndarray,
                ssd: np.ndarray, status: np.ndarray, taken: np.ndarray) -> int:
            found = int(_track_frame(prev.data, curr.data, prev.geo, pts, preds, hold, follow,
                                     taken, *settings, budget, pos, ssd, status))
            if found < 0:  # a point or prediction out of bounds, which the kernel refused
                _bad_coordinates(pts, preds)
            return found

        found = run(preds, hold, self._follow, pos, ssd, status, taken)
        lost = n_feat - found
        if self._guided_retry and n_feat >= MIN_GUIDES and lost > RETRY_GAIN * n_feat and (
                found < BROKEN * n_feat
                or (np.count_nonzero(taken) < BROKEN * np.count_nonzero(hold)
                    and _broke(pts, preds, pos, status, self._search_half))):
            # most predictions broke, or most features tracked before did not follow and the
            # matches found moved otherwise than they predicted: track every feature again
            # around the frame-wide shift, where it differs from the predictions, and keep the
            # second run where it found clearly more (RETRY_MARGIN)
            shift = frame_shift(prev, curr)
            guided = None if shift is None else pts + shift
            # (the retry's own predictions, not the caller's: a point at the edge of
            # +-MAX_COORD moved by the shift is not retried, rather than refused as if the
            # caller had given it)
            if shift is not None and guided is not None and \
                    bool((np.abs(guided) <= MAX_COORD).all()) and \
                    np.abs(np.median(preds - pts, axis=0) - shift).max() >= 2.0:
                pos2, ssd2 = np.empty_like(pos), np.empty_like(ssd)
                status2 = np.empty_like(status)
                none = np.zeros(n_feat, np.bool_)
                if run(guided, none, False, pos2, ssd2, status2,
                       np.zeros(n_feat, np.bool_)) > found + RETRY_MARGIN * n_feat:
                    pos, ssd, status = pos2, ssd2, status2
                    taken[:] = False
        return pos, ssd, status


def _bad_coordinates(pts: np.ndarray, preds: np.ndarray) -> None:
    """Raise the error that names the first of ``pts`` or ``preds`` not finite within
    +-MAX_COORD (:func:`_track_frame` refused them: the check costs nothing in the kernel,
    where four numpy calls a frame cost ~40 us in a service, each from cold caches)."""
    _within(pts, "points")
    _within(preds, "predictions")
    raise AssertionError("_track_frame refused coordinates that are all within bounds")


def _broke(pts: np.ndarray, preds: np.ndarray, pos: np.ndarray, status: np.ndarray,
           reach: float) -> bool:
    """Whether the matches found (``status`` OK, at least one) moved, by their median
    displacement, more than ``reach`` px (the frame level's search) otherwise than the median
    prediction: the predictions broke, though enough features were found around them or
    around the motion of the few found first (the step back after a jump: 38 of 50 found, the
    rest searched around a median of 3 matches, 26.9 px off, their windows off the frame). A
    bound of DOMINANT_PX also caught the smooth accelerations of the rendered sequences,
    whose retries then lost Dimetrodon's 3 % of its tracked pairs. Asked only where most
    features tracked before did not follow; :func:`_dominant` is warm (the tracker's own)."""
    gx, gy = _dominant(pts, pos, status)
    px, py = _dominant(pts, preds, np.zeros(len(pts), np.int8))
    return bool(abs(gx - px) > reach or abs(gy - py) > reach)


def frame_shift(prev: Pyramid, curr: Pyramid) -> np.ndarray | None:
    """The frame-wide translation from frame t to frame t+1, (dx, dy) px, by phase
    correlation (``cv2.phaseCorrelate``, Hann-windowed) at the coarsest level whose sides are
    at least SHIFT_SIDE px (the frame itself if it is smaller), halved further while its
    shorter side exceeds SHIFT_MAX_SIDE; None where the frames show no peak (a flat frame)
    or the peak lies off the level.

    Its reach is a good part of the frame at any speed (a third of the level's side with the
    window's taper), where the search's is SEARCH_SIZE // 2 pixels of the coarsest level: the
    guide for a frame that broke its features' predictions. It sees one translation: a
    rotation or a zoom blurs the peak, and the retry's searches, with all their tests, decide
    what it is worth.
    """
    k = prev.levels - 1
    while k > 0 and min(prev.shapes[k]) < SHIFT_SIDE:
        k -= 1
    h, w = prev.shapes[k]
    if min(h, w) < 4:
        return None
    a8, b8 = prev.level(k), curr.level(k)
    while min(h, w) > SHIFT_MAX_SIDE:
        h, w = h // 2, w // 2
        a8 = cv2.resize(a8, (w, h), interpolation=cv2.INTER_AREA)
        b8 = cv2.resize(b8, (w, h), interpolation=cv2.INTER_AREA)
    # without their means: the window's own spectrum, left in, peaks at no shift
    a = a8.astype(np.float32)
    a -= a.mean()
    b = b8.astype(np.float32)
    b -= b.mean()
    (dx, dy), response = cv2.phaseCorrelate(a, b, _hann(h, w))
    if not (response > 0.0 and abs(dx) < w / 2 and abs(dy) < h / 2):
        return None
    kh, kw = prev.shapes[k]
    return np.array([dx * kw / w, dy * kh / h]) * 2.0 ** k


@functools.lru_cache(maxsize=8)
def _hann(h: int, w: int) -> np.ndarray:
    return cv2.createHanningWindow((w, h), cv2.CV_32F)
