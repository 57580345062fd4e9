"""Relay hub: the accelerated hub form of consensus ADMM on a sparse graph, one robot's sans-IO core.

Why it exists: on a complete graph every robot hears every robot, so each runs the fleet's hub
ADMM with Anderson acceleration (agents/admm.py ``_Hub``), 2-5 times fewer rounds than the edge
form. On a sparse graph the edge form was the only exact choice. Here every robot *relays*: its
frame carries, for every robot l of the fleet, the newest a_l it holds, so robot i holds a_l with a
delay of d(i, l) hops (deterministic in lockstep). Every robot then runs one identical copy of the
whole fleet's Douglas-Rachford (hub ADMM) state, stepped with the values of round k - D (D the
graph's diameter, which every robot holds from every robot):

    fleet state S = (t_1 .. t_N)             t_l: robot l's proximal centre (z - u_l in hub terms)
    x_l = argmin f_l(v) + 1/2 (v - t_l)' P (v - t_l)      (robot l's own QP; only l computes it)
    a_l = 2 x_l - t_l                        (the one vector robot l publishes, relayed by all)
    F(S)_l = t_l + eta (mean_j a_j - x_l)    (the relaxed Douglas-Rachford map, eta = RELAY_RELAX)
    S^(k+1) = Anderson(F(S^(k+1-D)), history of (S^j, F(S^j)))    (type-II, safeguarded)

Every copy knows every t_l (it computed S), so x_l = (a_l + t_l) / 2 needs only the relayed a_l:
frames carry N vectors of M + 1 floats (N <= RELAY_MAX_ROBOTS = 16: the frame budget of 16 (M + 1)).
Robot i keeps its own block t_i of the copy's S and solves its own QP at it.

Exact: each pair (S^j, F(S^j)) is an exact evaluation of the one fleet map F (every x_l is robot
l's own prox of its own t_l), Anderson's result is an affine combination of such evaluations, and
at a fixed point F(S) = S: mean_j a_j = x_l for every l, so all x_l equal one z, sum_l t_l = N z and
0 in sum_l (df_l(z) + P (z - t_l)) = sum_l df_l(z): the centralized optimum (as agents/free_hub.py
argues for the free hub). The delay changes the path, not the fixed point.

Bit-identical copies: every operation that mixes robots is elementwise in robot-id order or exactly
rounded (admm.py's ``_pairwise_sum`` and ``_solve_spd``), so every robot's copy of S is the same
bits on any machine -- which is what lets robot i take t_l from its own copy instead of the frame.

What the frames reveal: a_l of every robot reaches every robot (relayed through the graph), not only
the neighbours' values as in the edge form. a_l is a function-space vector (M + 1 floats), never a
point or a feature row; but a robot learns every other robot's iterates, a privacy change versus the
paper (where a robot sees its neighbours' values only). A compromised neighbour can forge the a_l
it relays (the frames are authenticated per edge, not end to end), and so steer the fleet to a wrong
point -- as it can in the edge form by sending a wrong own value; a garbled frame of the wrong size
is refused by the round protocol (`RoundCore.receive`), and a non-finite relayed value makes the
step fail as a local solve would (the session stops the robot with the reason, no traceback).

Stop: every copy computes the fleet's residual of round k - D (the x_l's spread around their mean,
the mean's move) and the stop tests of `relay_stop_tests` on it -- margin x r / (1 - rate) over two
windows below tol for a hold of rounds in a row (a delayed Anderson can sit on a plateau a short hold
would stop on, see docs/algorithm.md): without the certified guard, main's test (2 x over windows of 20,
held 40) or a faster one (3 x over windows of 10, held 24), whichever holds first; where the guard
decides, main's test held 5 rounds and its bound. Every copy computes that test from the same bits in
the same round, so it is the fleet's verdict: the robots stop in the round it passes, without the D flag
rounds of the other round-based cores (`RoundCore.fleet_wide_verdict`).

Anderson's design (memory RELAY_MEMORY, relaxation RELAY_RELAX, regularisation RELAY_REG): with
delay D the D newest iterates are in flight when S^(k+1) is formed, so a window of m secant pairs
spans about m / D extrapolations; a longer memory than the complete graph's and a stronger
relaxation took fewer rounds on every relay fleet of rounds.md (docs/algorithm.md, the sweep in
benchmarks/results/rounds-stop-relay.md). The path is chaotic in these constants (the 16-ring at
memory 45 / 50 / 55: 1170 / 1070 / 1411 rounds), so they were chosen on sums over many fleets.

Certified guard (admm's `certify`, hard margins, where N (M + 1 + 6) floats fit the frame budget):
robot l's 6 certificate floats (agents/certificate.py) ride in its slot beside a_l -- the
multipliers of its step at t_l and the margins at the mean centre of S^j (the mean of the t_l it
has just stepped from, for the a_l of round j; since branch certtight, the mean x of round j - D
before) -- and every copy computes the fleet certificate of round j from them, grad_l = (P + 1/N
on x) x_l - P t_l, x_l = (a_l + t_l) / 2; the stop also needs its bound over the x_l of round j <=
admm.certify_threshold. Any feasible point whose margins every robot reported and any multipliers
>= 0 bound the error (docs/algorithm.md), so any point every copy holds will do.

Exact end-game (RELAY_ENDGAME, hard margins; branch ringend): the frames are full, so an end-game step cannot
ride beside the ADMM; the fleet pauses it instead. Every copy watches every robot's step (W_l = A_l' lam_l from
held values, `step_normals`): once no robot's step changed its piece (`piece_changed`) for RELAY_ENDGAME_QUIET
fleet steps and the stop tests' estimate is below RELAY_ENDGAME_ESTIMATE, every robot -- in the same round, from
the same bits -- keeps its step's multipliers, guesses its rows' active set and starts an attempt of
agents/soft_endgame.py's block Krylov end-game (C = inf; its start block widened by the robots' step
multipliers, RELAY_ENDGAME_BLOCK). Each end-game step is one gather of every robot's
payload (payload_size(M + 1) = 70 floats on the paper grid; `relay_endgame_plan`: 2 per frame, D rounds on a
ring, shells of 4 in two rounds on the 16-geo fleet) in the frames of the paused rounds, padded to the fleet's one
frame length; every robot folds the same rows in id order. All robots certify their rows: every robot holds the
exact optimum bit for bit and the fleet stops (the verdict is every copy's). The attempt's first fresh guess
ends it: the ADMM resumes from the round it paused at, its state and the a's in flight untouched (`_lround`:
the protocol's round less the paused ones), and the next attempt waits RELAY_ENDGAME_GAP ADMM rounds. Soft margins
(RELAY_SOFT_ENDGAME, branch relaysoft) run the same attempt with their finite C (the same 70-float payload) where a
step's gather takes at most RELAY_SOFT_STEP_ROUNDS rounds; their piece test is `piece_changed`'s soft form.

A robot that dies for good cannot be dropped consistently (its relays are gone and the delays of
every path through it change): the relay robots then stop, not converged, with that reason; the
edge form (`relay = False` in the fleet's params) keeps its survivors' answer. No I/O, no clock.
"""

from __future__ import annotations

import math
from collections import OrderedDict
from collections.abc import Mapping, Sequence
from dataclasses import replace
from typing import Any

import numpy as np

from agents import admm
from agents import certificate as cert_math
from agents.admm import (FRAME_BUDGET, RATE_WINDOW, ADMMParams, _digest, _pairwise_sum, _solve_spd, certify_slot,
                         certify_threshold, error_estimate, shared_step)
from agents.certificate import Certificate, fleet_certificate
from agents.allreduce import AllReduce, ReducePlan, _bfs, check_graph
from agents.messages import StateUpdate
from agents.problem import MarginQP, SolverError
from agents.rounds import RobotShare, RoundCore, from_bytes, relative_gaps, to_bytes
from agents.soft_endgame import SoftEndgame, payload_size
from protocol.frames import MAX_DIM

#: the frame budget: N vectors of M + 1 floats, at most FRAME_BUDGET (M + 1)
RELAY_MAX_ROBOTS = FRAME_BUDGET
#: relaxation eta of the Douglas-Rachford map (1: plain ADMM); 1.5 before branch relayaa
RELAY_RELAX = 1.7
#: Anderson's memory (secant pairs kept) on the relay hub; ADMMParams.anderson is the complete
#: graph's (30). With delay D the D newest iterates are still in flight, so a window of m pairs spans
#: about m / D extrapolation steps: 50 with eta 1.7 took seven relay fleets (4-ring .. 16-ring) from
#: 5905 rounds at stop to 4387 and the 36 runs of rounds.py --stop-check from 59742 to 57264 (main:
#: 30 pairs, eta 1.5; hold 40 in both; the sweep of memory, regularisation, relaxation and pair
#: selection: docs/algorithm.md, benchmarks/relay_anderson.py)
RELAY_MEMORY = 50
#: restart Anderson when the residual exceeds this x its best since the last restart. With delay D the
#: D - 1 points formed before a restart are still in flight after it, extrapolated by the history it has
#: just dropped: they count towards the best but restart nothing (branch ring16; restarting on them
#: dropped the new history for the old one's faults, a cascade of a restart about every D rounds -- 16-ring
#: seed 3: 121 restarts, 2450 rounds at stop, now 1832; benchmarks/results/rounds-stop-relay.md, top)
RELAY_SAFEGUARD = 10.0
#: Tikhonov regularisation of Anderson's least squares, relative to the mean diagonal
RELAY_REG = 3e-3
#: the stop tests (`relay_stop_tests`): margin x `admm.error_estimate` over windows of w rounds below tol for
#: `hold` rounds in a row; where no certified guard decides (N >= 12 on the paper grid, soft margins)
#: the fleet stops when either of two has held. Main's: 2 x over windows of RATE_WINDOW (20), held 40
#: rounds -- on the plateaus a delayed Anderson can sit on (error just above tol, the residual ~70x
#: below it, isolated spikes in the older window faking a fast rate) it passed for at most 23 rounds in
#: a row on every traced run; the fast one (branch relaystop): 3 x over windows of 10, at most 14 in a
#: row there, held 24 -- main's ratio of hold to longest false streak (40 / 23, 24 / 14). Chosen offline
#: on traces (benchmarks/relay_anderson.py --trace / --replay, benchmarks/results/rounds-stop-relay.md):
#: either one's stop is within tol on every trace, so the earlier of the two is; never later than main
RELAY_STOP_MARGIN = 2.0
RELAY_HOLD = 40
RELAY_FAST_WINDOW = 10
RELAY_FAST_MARGIN = 3.0
RELAY_FAST_HOLD = 24
#: the hold of main's test where the certified guard decides too (`relay_cert_slot`, hard margins: N <=
#: 11 on the paper grid): the stop then also needs the proven bound <= certify_threshold, which refuses
#: the known plateaus by itself (bound 0.16 on the one at 1.1e-3; even hold 1 kept every guarded stop
#: safe, branch relayaa2), so the rule only proposes: 5 since branch relaystop (20 before, 40 before
#: relayaa). The bound, not the hold, gates these stops: the 8-ring's first fell below 1e-2 at round
#: 616 (stop 620); with branch certtight's bound at round 598 (stop 602; 598 without the flag rounds)
RELAY_HOLD_CERTIFIED = 5
#: the exact warm-started local QP (admm.WARM_QP's KKT solve), only where the certified guard decides
#: (`_cert_on`, as the hub's WARM_QP + cert_active; piqp elsewhere): stays off. Measured with the relayaa
#: design (branch relayaa2, benchmarks/relay_anderson.py --warm-qp on): 8-ring 630 -> 757 rounds at stop,
#: 4-ring, 5-line, 6-ring, 8-ring seeds 0-4 9320 -> 9869, the 36 runs of --stop-check 31 -> 29 stops
#: (cross ring 6 s0 and star ring 6 s2 then hit the 5000 cap); the 16-robot fleets have no guard
RELAY_WARM_QP = False
#: the exact end-game on a paused relay (hard margins; docs/algorithm.md, the relay hub, "The paused end-game"):
#: the fleet pauses its ADMM for an attempt of agents/soft_endgame.py's block Krylov end-game (C = inf), one
#: exact all-reduce of every robot's payload per end-game step (a gather, `relay_endgame_plan`), and
#: either certifies the exact optimum (the fleet stops) or resumes the ADMM where it paused. Measured on
#: the six relay fleets x seeds 0-5 (branch ringend; benchmarks/relay_anderson.py --endgame on|off, the rule
#: chosen on seeds 0-2 with benchmarks/relay_endgame.py's attempts): every run certified, 35 of 36 earlier
#: (6-ring seed 5 398 -> 438), 33058 -> 19101 rounds, 16-ring 1918 -> 861 on an AVX-512 machine
RELAY_ENDGAME = True
#: the same paused end-game on soft margins (finite C: SoftEndgame's B rows at the box; the piece test then
#: compares the two steps' W difference, `piece_changed`'s soft form), on fleets whose end-game step (one gather)
#: takes at most RELAY_SOFT_STEP_ROUNDS rounds. Measured (branch relaysoft, benchmarks/relay_anderson.py --C 1
#: 10 100 --soft-endgame on|off, seeds 0-2): 4-, 6-, 8-ring and 5-line 36 of 36 runs earlier, 14856 -> 11414
#: rounds at stop, every attempt certified; the 16-robot fleets (8 and 7 rounds a step) 19357 -> 19190 but 8 of 18 runs later, up to
#: +521 (attempts there paused up to 546 rounds, 16-geo seed 1 C 1: two attempts): off there
RELAY_SOFT_ENDGAME = True
#: the paused end-game's block (Krylov vectors per step; soft_endgame.BLOCK = 3, the complete graphs', so the
#: payload and frames are theirs) with its start block filled (`SoftEndgame(wide_start=True)`: the preconditioned
#: 1 and t, then each robot's step multipliers on its E rows; a wide solve ended off the answer with nothing to
#: move is solved again from the narrow start). A larger block alone changes nothing (the widest block a step
#: sends is the start block's: 2 vectors, 3 with soft g; the same bits at 5). Measured (branch relayblock,
#: benchmarks/relay_anderson.py, six relay fleets x seeds 0-5): AVX-512 19101 -> 18045 rounds, all 36 earlier;
#: AVX2 17725 -> 16668, 35 earlier, 6-ring seed 4 250 -> 280; start blocks filled to 4-6 (then w A_E[:, j])
#: 17701 / 17212 / 17138 on AVX-512 but 6-ring seed 4 278 -> 355-361
RELAY_ENDGAME_BLOCK = 3
#: the soft end-game's fleets: one end-game step (a gather, `relay_endgame_plan`) in at most this many rounds
RELAY_SOFT_STEP_ROUNDS = 4
#: an attempt starts when no robot's step changed its piece (active set, `piece_changed`: every copy sees it
#: from held values) for this many fleet steps in a row ...
RELAY_ENDGAME_QUIET = 40
#: ... and the stop tests' smallest estimate (`RelayHubADMM.estimate`) is below this (it excludes the
#: rounds just after an Anderson restart, estimate inf, where the copy's piece test compares new steps)
RELAY_ENDGAME_ESTIMATE = 3.0
#: ADMM rounds after an attempt that did not certify before the next may start
RELAY_ENDGAME_GAP = 100
#: attempts per run at most; then the ADMM alone finishes (its iterates are the ADMM-alone path, so the run
#: stops at most the paused rounds of these attempts later than without the end-game). On the 72 hard relay
#: runs measured (seeds 0-11, branches ringend and relaysoft) every certified run certified by its second
#: attempt; the two that did not (16-ring seed 8: 5 attempts, 3208 paused rounds, 4577 at stop against 2058
#: alone; 16-geo seed 8: 5 attempts, 3290 paused, the 5000-round cap, NOT converged, against 2587 alone)
#: waited out failed attempts of ~640 paused rounds each
RELAY_ENDGAME_TRIES = 2
#: end-game steps after which an attempt that has not certified ends (the ADMM resumes); inf: none. Measured on
#: fresh seeds 6-11 (branch relaysoft, benchmarks/relay_anderson.py --max-steps): 20 ended attempts that certify
#: (27 runs 14887 -> 14651 but 10 later, up to +940); 70 cut the 16-geo's 79-step certified attempts (+205)
RELAY_ENDGAME_MAX_STEPS: float = math.inf
#: an attempt whose first solve leaves more than this many robots with a violated row ends there (its guess
#: judged: one row moves per correction); inf: never. Measured on seeds 6-11 (--judge): 5 took 36 runs 27905 ->
#: 28225 rounds (3 later, up to +183), 2 far worse: the guesses that certify often start far off
RELAY_ENDGAME_JUDGE: float = math.inf
#: W_l below this fraction of its two terms is the step solver's noise: no active row (`step_normals`).
#: piqp's steps on the 16-ring leave W_l up to 3.5e-7 of its terms with no row within 5e-2 of its margin
NORMAL_FLOOR = 1e-5
#: the piece test's threshold on |W . (x - x_prev)| relative to |W| |x| (`piece_changed`)
PIECE_TOL = 1e-6


#: fleet steps taken lately in this process, by the digest of a copy's token and the step's inputs:
#: every robot's copy takes the identical step, so the robots of one process (the in-process fleet)
#: compute it once and adopt it (the same bits); a step no longer here is computed again
_SHARED: OrderedDict[bytes, tuple[Any, ...]] = OrderedDict()
SHARED_KEPT = 64
#: the guard's certificates computed lately in this process (`RelayHubADMM._certify`), as _SHARED
_SHARED_CERTS: OrderedDict[bytes, tuple[Any, ...]] = OrderedDict()


def relay_stop_tests(guarded: bool) -> tuple[tuple[int, float, int], ...]:
    """The relay's stop tests as (window, margin, hold): the fleet's stop test passes once any of them
    has had margin x error_estimate(window) below tol for hold rounds in a row; `guarded`: the certified
    guard decides too (its bound is then needed as well). See the constants."""
    if guarded:
        return ((RATE_WINDOW, RELAY_STOP_MARGIN, RELAY_HOLD_CERTIFIED),)
    return ((RATE_WINDOW, RELAY_STOP_MARGIN, RELAY_HOLD), (RELAY_FAST_WINDOW, RELAY_FAST_MARGIN, RELAY_FAST_HOLD))


def relay_stop_held(held: Sequence[int], residuals: list[float], tests: Sequence[tuple[int, float, int]],
                    tol: float) -> tuple[int, ...]:
    """One round of the stop tests: each test's count of passing rounds in a row, after the newest
    residual (margin x the estimate over its window below tol: one more; otherwise 0)."""
    return tuple(h + 1 if margin * error_estimate(residuals, window=w) < tol else 0
                 for h, (w, margin, _) in zip(held, tests))


def relay_stop_passed(held: Sequence[int], tests: Sequence[tuple[int, float, int]]) -> bool:
    """True once any stop test has passed for its hold."""
    return any(h >= hold for h, (_, _, hold) in zip(held, tests))


def relay_memory(params: ADMMParams, n: int, dim: int, delay: int) -> int:
    """Anderson's memory on the relay hub: RELAY_MEMORY for every fleet (`anderson` > 0 turns the
    relay on; its value is the complete graph's memory). A function so that a sweep
    (benchmarks/relay_anderson.py) can try rules in N, dim and the delay D."""
    return RELAY_MEMORY


def step_normals(pdiag: np.ndarray, P: np.ndarray, X: np.ndarray, T: np.ndarray) -> np.ndarray:
    """Every robot's W_l = (P + 1/N on x) x_l - P t_l, row by row (`pdiag`: P + 1/N on x): by its step's KKT
    conditions A_l' lam_l, the combination of robot l's active margin rows by their multipliers -- what every
    copy computes from the relayed a_l (x_l = (a_l + t_l) / 2) and its own t_l, no row leaving the robot. A
    W_l at the solver's noise (below NORMAL_FLOOR of its terms) is zero: no active row."""
    W = pdiag * X - P * T
    scale = np.linalg.norm(pdiag * X, axis=1) + np.linalg.norm(P * T, axis=1)
    return np.where((np.linalg.norm(W, axis=1) <= NORMAL_FLOOR * scale)[:, None], 0.0, W)


def piece_changed(X_prev: np.ndarray, W_prev: np.ndarray, X: np.ndarray, W: np.ndarray, *,
                  soft: bool = False) -> np.ndarray:
    """Per robot: True when its two consecutive steps lie on different affine pieces of its step map, seen
    from held values only. On one piece (active set A_W) the step is the projection, in the metric of
    (P + 1/N on x), of P t / (P + 1/N on x) onto the face {A_W v = 1}: both W's are combinations of the
    face's rows, so W . (x - x_prev) = W_prev . (x - x_prev) = 0; a row that enters or leaves breaks one
    of them by its margin gap. Relative to |W| |x| (PIECE_TOL): piqp's answers are exact to ~1e-10.
    `soft` (finite C): W also holds C x the rows at the box (B), fixed on a piece but not orthogonal to the
    move, so the test is on the difference, (W - W_prev) . (x - x_prev) = (lam_E - lam_E_prev)' A_E dx = 0 on
    one piece; a row entering or leaving E breaks it by its multiplier's change x its margin gap."""
    dX = X - X_prev
    if soft:
        num = np.abs(np.sum((W - W_prev) * dX, axis=1))
    else:
        num = np.maximum(np.abs(np.sum(W * dX, axis=1)), np.abs(np.sum(W_prev * dX, axis=1)))
    scale = np.maximum(np.linalg.norm(W, axis=1), np.linalg.norm(W_prev, axis=1)) * np.linalg.norm(X, axis=1)
    return num > PIECE_TOL * np.maximum(scale, 1e-300)


def relay_endgame_plan(graph: Mapping[int, Sequence[int]], robot: int, dim: int) -> ReducePlan | None:
    """The end-game's all-reduce on a relay fleet: a gather of every robot's payload (payload_size(dim,
    RELAY_ENDGAME_BLOCK) floats), at most as many per frame as the frame budget (FRAME_BUDGET x dim) and MAX_DIM
    allow -- and of those, the fewest that keep its fewest rounds (16-geo: 2 per frame, 7 rounds). None when
    not one payload fits."""
    size = payload_size(dim, RELAY_ENDGAME_BLOCK)
    cap = min(FRAME_BUDGET * dim, MAX_DIM) // size
    if cap < 1:
        return None
    fewest = ReducePlan.build(graph, robot, "gather", cap).rounds
    slots = min(c for c in range(1, cap + 1) if ReducePlan.build(graph, robot, "gather", c).rounds == fewest)
    return ReducePlan.build(graph, robot, "gather", slots)


def relay_endgame_on(graph: Mapping[int, Sequence[int]], dim: int, hard: bool) -> bool:
    """True when a relay fleet runs the paused end-game: RELAY_ENDGAME, a payload that fits, and a hard margin
    -- or a soft one with RELAY_SOFT_ENDGAME where a step's gather takes at most RELAY_SOFT_STEP_ROUNDS rounds."""
    plan = relay_endgame_plan(graph, min(graph), dim) if RELAY_ENDGAME else None
    return plan is not None and (hard or (RELAY_SOFT_ENDGAME and plan.rounds <= RELAY_SOFT_STEP_ROUNDS))


def relay_cert_slot(params: ADMMParams, n: int, dim: int) -> bool:
    """True when relay frames carry every robot's certificate payload beside its a (the guard,
    admm.certify_slot): N (dim + PAYLOAD) floats must fit the frame budget of FRAME_BUDGET x dim
    floats and a frame's MAX_DIM (N <= 11 on the paper grid); larger fleets stop by the rule alone."""
    size = n * (dim + cert_math.PAYLOAD)
    return certify_slot(params) and size <= FRAME_BUDGET * dim and size <= MAX_DIM


def relay_frame_dim(params: ADMMParams, n: int, dim: int, graph: Mapping[int, Sequence[int]] | None = None,
                    hard: bool = False) -> int:
    """A relay frame's length: N slots of a_l (dim floats), each followed by robot l's certificate
    payload when the guard's slot fits (`relay_cert_slot`); with the end-game (`relay_endgame_on`, given the
    graph and a hard margin) at least its all-reduce's frame (`relay_endgame_plan`: slots x payload_size), zero-padded:
    every frame of a fleet has one length, whatever a round carries."""
    relay = n * (dim + (cert_math.PAYLOAD if relay_cert_slot(params, n, dim) else 0))
    if graph is None or not relay_endgame_on(graph, dim, hard):
        return relay
    plan = relay_endgame_plan(graph, min(graph), dim)
    assert plan is not None
    return max(relay, plan.slots * payload_size(dim, RELAY_ENDGAME_BLOCK))


def relay_form(params: ADMMParams, graph: Mapping[int, Sequence[int]], dim: int) -> bool:
    """True when a fleet's ADMM runs the relay hub: a sparse graph of 3 to 16 robots, Anderson on
    (anderson > 0), `relay` set (the default) and N frames of (x, gamma) (`dim` floats each) within
    a frame's MAX_DIM. Complete graphs keep the hub form, the others the edge form."""
    n = len(graph)
    complete = all(len(set(nbrs)) == n - 1 for nbrs in graph.values())
    fits = n * dim <= MAX_DIM
    return bool(params.relay and params.anderson > 0 and 2 < n <= RELAY_MAX_ROBOTS and not complete and fits)


def hop_table(graph: Mapping[int, Sequence[int]]) -> dict[int, dict[int, int]]:
    """Hop distance between every two robots (breadth-first from each)."""
    return {i: _bfs(graph, i)[0] for i in graph}


class RelayHubADMM(RoundCore):
    """One robot of the relay hub (see the module); the round protocol's interface."""

    algorithm = "admm"
    #: every copy's stop test (the estimate on the fleet residual of round k - D, the guard's bound) is the
    #: same bits in the same round, so the fleet stops in the round it passes, without D flag rounds
    #: (a copy that differed would be a broken relay: robots left running then wait for frames that no
    #: longer come and end not converged, never a false success)
    fleet_wide_verdict = True

    def __init__(self, share: RobotShare, params: ADMMParams, *, graph: Mapping[int, Sequence[int]],
                 keep_trace: bool = True) -> None:
        check_graph(graph)
        me = share.robot_id
        if tuple(sorted(graph.get(me, ()))) != tuple(share.neighbours):
            raise ValueError(f"robot {me}: neighbours {share.neighbours} differ from the graph's {graph.get(me)}")
        if len(graph) > RELAY_MAX_ROBOTS:
            raise ValueError(f"the relay hub carries at most {RELAY_MAX_ROBOTS} robots per frame, not {len(graph)}")
        super().__init__(me, share.neighbours, share.dim, diameter=params.diameter, round_cap=params.max_rounds,
                         keep_trace=keep_trace)
        self.params = params
        self.ids = tuple(sorted(graph))
        self.n = n = len(self.ids)
        hops = hop_table(graph)
        self.delay = max(max(d.values()) for d in hops.values())  # D: every a_l is here after D rounds
        self._dist = hops[me]
        # slot l of my frame at round r holds a_l of round r - d(me, l); I read robot l's value from
        # the neighbour nearest to l (ties: lowest id), whose frame of round r holds round r - d(j, l)
        self._route = {l: min(self.neighbours, key=lambda j: (hops[j][l], j)) for l in self.ids if l != me}
        self._route_hops = {l: hops[j][l] for l, j in self._route.items()}
        # the certified guard (admm's certify; docs/algorithm.md "A certified stop"): robot l's
        # PAYLOAD floats ride beside its a_l, relayed alike; on where they fit the frame budget, and
        # it decides for hard margins only (as the hub's cert_active)
        self._cert_slot = relay_cert_slot(params, n, share.dim)
        self._cert_on = self._cert_slot and share.C is None
        self._tests = relay_stop_tests(self._cert_on)
        self._kept = 2 * max(w for w, _, _ in self._tests)  # residuals kept: the longest test's two windows
        width = share.dim + (cert_math.PAYLOAD if self._cert_slot else 0)
        self._slots = {l: slice(k * width, (k + 1) * width) for k, l in enumerate(self.ids)}  # l's [a; p] in a frame
        self._blocks = {l: slice(k * share.dim, (k + 1) * share.dim) for k, l in enumerate(self.ids)}  # t_l in S
        self.frame_dim = relay_frame_dim(params, n, share.dim, graph, share.C is None)
        self._relay_dim = n * width
        self._P = np.full(self.dim, params.rho)
        self._P[-1] *= params.gamma_penalty
        self._pdiag = cert_math.step_diagonal(self._P, n)  # the step QP's diagonal (1/N on x)
        self._w = np.tile(np.sqrt(self._P), n)  # Anderson's residual weights (the P-norm)
        self._memory = relay_memory(params, n, share.dim, self.delay)
        self._qp = MarginQP(share.features, share.labels, x_weight=1.0 / n, prox_weight=self._P, C=share.C)
        # the paused end-game (RELAY_ENDGAME, hard margins): its attempt state, the all-reduce of its payloads,
        # and the rounds paused so far -- the ADMM's own round is `_lround` = round - paused
        self._endgame: SoftEndgame | None = None
        self._reduce: AllReduce | None = None
        if relay_endgame_on(graph, share.dim, share.C is None):
            plan = relay_endgame_plan(graph, me, share.dim)
            assert plan is not None
            self._endgame = SoftEndgame(self._qp, self.ids, me, math.inf if share.C is None else share.C,
                                        block=RELAY_ENDGAME_BLOCK, wide_start=True)
            self._reduce = AllReduce(plan, payload_size(share.dim, RELAY_ENDGAME_BLOCK))
        self._mode = "admm"  # admm | endgame (an attempt: the frames carry the all-reduce) | certified
        self._paused = 0
        self._next_try = 0  # the ADMM round from which an attempt may start
        self._quiet = 0  # fleet steps in a row in which no robot's step changed its piece (`piece_changed`)
        self._pieces: tuple[np.ndarray, np.ndarray] | None = None  # the last step's X and W (`step_normals`)
        self._attempt_base = 0  # the end-game's attempt count when this attempt started
        self._attempt_steps = 0
        self._attempt_v: np.ndarray | None = None  # my step at the attempt's start (its guess reads it)
        self._attempt_lam: np.ndarray | None = None  # that step's multipliers (restored with a checkpoint)
        self._reduce_frame: np.ndarray | None = None  # the all-reduce's frame of this round
        self._attempts = 0
        self._certificate: Certificate | None = None  # the last fleet certificate computed
        self._fleet_bound = math.inf
        if self._cert_on:
            self._sides = cert_math.sides(self._qp._rows)
        self._broken: str | None = None
        # the shared fleet state by round (rounds k - D .. k), the relayed a's by robot and round
        self._S: dict[int, np.ndarray] = {}
        self._a: dict[int, dict[int, np.ndarray]] = {l: {} for l in self.ids}
        self._forget()
        self._fresh = self.delay  # steps since the last restart, up to D: no restart yet, the safeguard is armed
        # digest of everything the copy's state follows from (see _SHARED); the data enter by S^0
        self._token = _digest(repr((self.ids, self.dim, self.delay, params.rho, params.gamma_penalty, params.tol,
                                    self._memory, RELAY_RELAX, RELAY_SAFEGUARD, RELAY_REG,
                                    self._tests, self._endgame is not None, NORMAL_FLOOR, PIECE_TOL)).encode())
        self._residuals: list[float] = []
        self._held = (0,) * len(self._tests)  # consecutive rounds each stop test passed
        self._prev_mean: np.ndarray | None = None
        self._frame = np.zeros(self.frame_dim)
        self._prev_frame: np.ndarray | None = None
        # round 0: the robot's own max-margin solution, published as a with t = a = x (the start
        # S^0 = every robot's own solution, known to every copy from the relayed a's themselves)
        self._qp.set_prox(np.zeros(self.dim))
        try:
            own = self._solve(np.zeros(self.dim))
        finally:
            self._qp.set_prox(self._P)
        self._values = own
        self._a[me][0] = self._with_payload(own, None)  # (no step multipliers yet: no payload)
        self._frame = self._make_frame()
        self._record()

    # -- frames ---------------------------------------------------------------------------------
    @property
    def _lround(self) -> int:
        """The ADMM's own round: the protocol's round less the rounds its end-game attempts paused it."""
        return self.round - self._paused

    def _make_frame(self) -> np.ndarray:
        """Slot l: the newest a_l held, of ADMM round `_lround - d(me, l)` (zeros until it arrived); in an
        end-game attempt, the all-reduce's frame instead (zero-padded: every frame has frame_dim floats)."""
        frame = np.zeros(self.frame_dim)
        if self._mode != "admm":
            if self._reduce_frame is not None:
                frame[: len(self._reduce_frame)] = self._reduce_frame
            return frame
        for l in self.ids:
            a = self._a[l].get(self._lround - self._dist[l])
            if a is not None:
                frame[self._slots[l]] = a
        return frame

    def outgoing(self) -> StateUpdate:
        """The relay frame (every robot's newest a) instead of v; last round's frame piggybacked."""
        up = super().outgoing()
        return replace(up, values=self._frame.copy(),
                       prev_values=None if self._prev_frame is None else self._prev_frame.copy())

    # -- one round ------------------------------------------------------------------------------
    def _step(self, mine: np.ndarray, theirs: dict[int, np.ndarray]) -> tuple[np.ndarray, bool]:
        if self._broken is not None:
            raise SolverError(self._broken)
        if self._mode != "admm":
            return self._attempt_step(mine, theirs)
        k, D = self._lround, self.delay
        for l, j in self._route.items():  # round k's frames: a_l of round k - d(j, l) = k + 1 - d(me, l)
            stamp = k - self._route_hops[l]
            if stamp >= 0:
                a = theirs[j][self._slots[l]]
                if not np.all(np.isfinite(a[: self.dim])):  # (a bad payload: no certificate, no error)
                    raise SolverError(f"robot {j} relayed a non-finite value of robot {l}")
                self._a[l][stamp] = a.copy()
        below = False
        j = k + 1 - D
        if j >= 0:  # every a_l of round j is here: F(S^j), Anderson -> S^(k+1)
            held = np.array([self._a[l][j] for l in self.ids])
            A = np.ascontiguousarray(held[:, : self.dim])
            S = self._state(j)
            below = self._shared_step(S, A)
            if self._cert_on:  # the guard: the rule's stop also needs the certified bound
                self._fleet_bound = math.inf
                last = self.round + 1 >= self._round_cap  # (a capped run reports a bound too)
                if (below or last or admm.CERTIFY_EVERY_ROUND) and j >= D:  # (S^j: the payloads' centres)
                    self._certify(S, A, np.ascontiguousarray(held[:, self.dim :]), self._centre_mean(S))
                below = below and self._fleet_bound <= certify_threshold(self.params)
            t = self._S[k + 1][self._blocks[self.robot_id]]
        else:  # the first round's values are still on their way: t stays t^0 = the own solution
            t = self._a[self.robot_id][0][: self.dim]
        armed = self._cert_on and self._armed()
        start = self._start_attempt(k, below)
        self._qp.keep_multipliers = armed or start
        x = self._solve(t, mine if RELAY_WARM_QP and self._cert_on else None)
        a = 2.0 * x - t
        mean = self._centre_mean(self._S[k + 1]) if armed and j >= 0 else None
        self._a[self.robot_id][k + 1] = self._with_payload(a, t, mean)
        self._prune(k + 1 - D)
        if start:
            self._begin_attempt(x)
        return x, below

    # -- the paused end-game ---------------------------------------------------------------------
    def _start_attempt(self, k: int, below: bool) -> bool:
        """The fleet's verdict (the same bits on every copy) that an end-game attempt starts after this
        round's step: no robot's step changed its piece for RELAY_ENDGAME_QUIET fleet steps, the stop tests'
        estimate below RELAY_ENDGAME_ESTIMATE, RELAY_ENDGAME_GAP ADMM rounds since a failed attempt, fewer than
        RELAY_ENDGAME_TRIES attempts so far, and the ADMM not stopping now."""
        return (self._endgame is not None and not below and k + 1 >= self._next_try
                and self._attempts < RELAY_ENDGAME_TRIES
                and self._quiet >= RELAY_ENDGAME_QUIET and self.estimate() < RELAY_ENDGAME_ESTIMATE)

    def _begin_attempt(self, x: np.ndarray) -> None:
        """Pause the ADMM (its state waits at ADMM round k + 1, the a's in flight held): guess my rows' active
        set from this step's multipliers and solution, and start the first all-reduce of the payloads."""
        eg, red = self._endgame, self._reduce
        assert eg is not None and red is not None
        self._attempt_base = eg.attempts
        self._attempt_steps = 0
        self._attempt_v = x.copy()
        lam = self._qp.multipliers
        self._attempt_lam = None if lam is None else lam.copy()
        self._attempts += 1
        eg.guess(self._attempt_v)
        self._reduce_frame = red.begin(eg.payload)
        self._mode = "endgame"

    def _attempt_step(self, mine: np.ndarray, theirs: dict[int, np.ndarray]) -> tuple[np.ndarray, bool]:
        """A paused round: one round of the all-reduce; at its end one end-game step on every robot's
        payload (rows in id order, exact copies): certified -- the exact optimum, the fleet stops now; the
        attempt over (its first fresh guess: agents/soft_endgame.py) -- the ADMM resumes where it paused
        (from the next round); else the next payload's all-reduce begins."""
        eg, red = self._endgame, self._reduce
        assert eg is not None and red is not None and self._attempt_v is not None
        if self._mode == "certified":
            return mine, True
        size = red.frame_size
        frame = red.step({j: theirs[j][:size] for j in self.neighbours})
        self._paused += 1
        if not red.done:
            self._reduce_frame = frame
            return mine, False
        self._attempt_steps += 1
        corrections = eg.corrections
        done = eg.step(red.contributions(), self._attempt_v)
        if done is not None:  # every robot certified its rows: the exact optimum, the same bits everywhere
            self._mode = "certified"
            self._reduce_frame = np.zeros(size)
            return done.copy(), True
        over = eg.attempts != self._attempt_base + 1 or eg.kind == "wait"  # a fresh guess: the attempt is over
        if not over and eg.corrections == 1 and corrections == 0:  # its first solve ended violated: judge it
            over = int(np.count_nonzero(red.contributions()[:, 1] > 0.0)) > RELAY_ENDGAME_JUDGE
        if over or self._attempt_steps >= RELAY_ENDGAME_MAX_STEPS:  # (or its steps are spent)
            self._mode = "admm"
            self._next_try = self._lround + 1 + RELAY_ENDGAME_GAP  # (_lround + 1: the ADMM round it resumes at)
            self._reduce_frame = None
            return mine, False
        self._reduce_frame = red.begin(eg.payload)
        return mine, False

    # -- the certified guard --------------------------------------------------------------------
    def _armed(self) -> bool:
        """True when my payload of this step (round k + 1) can decide: the copies read it in round
        k + D, where a stop needs a test's hold (RELAY_HOLD_CERTIFIED) of passing rounds in a row -- and
        each _held grows by at most one a round -- or it is a capped run's last round. The same on every
        copy (_held is the copy's); admm.CERTIFY_ARM = inf: every round (tests, the benchmark's --check).
        Elsewhere zeros go out."""
        D = self.delay
        near = any(h + D >= hold for h, (_, _, hold) in zip(self._held, self._tests))
        return admm.CERTIFY_ARM == math.inf or near or self.round + D + 1 >= self._round_cap

    def _centre_mean(self, S: np.ndarray) -> np.ndarray:
        """The guard's primal point for the a's of round j: the mean of the centres t_l of S^j, which
        robot l holds when it steps to a_l of round j and every copy holds when it certifies round j
        (D rounds fresher than the mean x of round j - D used before branch certtight: at the fixed
        point sum_l t_l = N z, so it tends to the optimum alike). Row after row in id order."""
        return np.add.reduce(S.reshape(self.n, self.dim), axis=0) / self.n

    def _with_payload(self, a: np.ndarray, t: np.ndarray | None, mean: np.ndarray | None = None) -> np.ndarray:
        """My slot of the frames: a, and with the guard's slot my certificate payload of this step
        (margins at `mean`, the mean centre of this step's S, which every copy holds; zeros where
        there is none)."""
        if not self._cert_slot:
            return a
        lam = self._qp.multipliers
        if not self._cert_on or t is None or mean is None or lam is None:
            return np.concatenate([a, np.zeros(cert_math.PAYLOAD)])
        # grad = P x + q of my step (P: 1/N + rho on x; q = -P_prox t), at x = (a + t) / 2 exactly as
        # every copy rebuilds it (`_certify`): my residual then covers the copies' gradient bit for bit
        grad = self._pdiag * (0.5 * (a + t)) - self._P * t
        return np.concatenate([a, cert_math.robot_payload(self._qp._rows, self._sides, lam, grad, mean)])

    def _certify(self, S: np.ndarray, A: np.ndarray, payloads: np.ndarray, mean: np.ndarray) -> None:
        """The fleet's certificate of round j (agents/certificate.py): every robot's payload of its
        step at S^j (multipliers; margins at `mean`, the mean centre of S^j), the x part of sum_l
        grad_l with x_l = (a_l + t_l) / 2 and t_l from S^j; its bound over those x_l. Any feasible
        point whose margins every robot reported and any multipliers >= 0 give a valid bound. The
        same bits on every copy; computed once per process (`_SHARED_CERTS`)."""
        d, n = self.dim, self.n

        def compute() -> tuple[Certificate | None, float]:
            T = S.reshape(n, d)
            X = 0.5 * (A + T)
            grads = self._pdiag * X - self._P * T
            cert = fleet_certificate(payloads, mean[:-1], _pairwise_sum(grads)[:-1])
            return cert, (math.inf if cert is None else cert.fleet_bound(X))

        key = _digest(b"cert", self._token, S, A.ravel(), payloads.ravel(), mean)
        (cert, bound), _ = shared_step(_SHARED_CERTS, key, compute, SHARED_KEPT)
        self._fleet_bound = bound
        if cert is not None:  # (an older certificate stays a valid proof)
            self._certificate = cert

    def error_bound(self) -> float | None:
        """A proven upper bound on this robot's function error against the exact optimum, from the
        last fleet certificate (as the hub core's); None where there is none (guard off, soft margin)."""
        return cert_math.reported_bound(self._certificate if self._cert_on else None, self._values)

    def result(self) -> dict[str, Any]:
        # endgame as the hub core's (agents/admm.py `ConsensusADMM.endgame`): certified -- the run ended on
        # the paused end-game's certified optimum --, not certified -- attempts ran --, None -- none ran
        endgame = "certified" if self._mode == "certified" else "not certified" if self._attempts else None
        return {**super().result(), "error_bound": self.error_bound(), "endgame": endgame}

    def advance(self) -> StateUpdate:
        """The round protocol's advance, then this round's relay frame."""
        self._prev_frame = self._frame
        super().advance()
        self._frame = self._make_frame()
        return self.outgoing()

    def _state(self, j: int) -> np.ndarray:
        """S^j; S^0 is every robot's own solution, which round 0 published as a (t = a = x), and
        S stayed S^0 until the first step (round D)."""
        if j < self.delay:
            if 0 not in self._S:
                self._S[0] = np.concatenate([self._a[l][0][: self.dim] for l in self.ids])
            return self._S[0]
        return self._S[j]

    def _snapshot(self) -> tuple[Any, ...]:
        """The copy's state after a step (arrays are never changed in place: copies may share them)."""
        return (list(self._hist_F), list(self._hist_g), self._dg, self._df, self._gram, self._best, self._fresh,
                self._S[self._lround + 1], self.residual, list(self._residuals), self._prev_mean, self._held,
                self._quiet, self._pieces)

    def _shared_step(self, S: np.ndarray, A: np.ndarray) -> bool:
        """`_fleet_step`, taken once per process: a copy with the same token and inputs adopts it."""
        key = _digest(self._token, S, A.ravel())

        def compute() -> tuple[Any, ...]:
            below = self._fleet_step(S, A)
            return (self._snapshot(), below)

        (snap, below), adopted = shared_step(_SHARED, key, compute, SHARED_KEPT)
        if adopted:
            (hist_F, hist_g, self._dg, self._df, self._gram, self._best, self._fresh, S_new, self.residual,
             residuals, self._prev_mean, self._held, self._quiet, self._pieces) = snap
            self._hist_F, self._hist_g, self._residuals = list(hist_F), list(hist_g), list(residuals)
            self._S[self._lround + 1] = S_new
        self._token = key
        return below

    def _fleet_step(self, S: np.ndarray, A: np.ndarray) -> bool:
        """F at S (x_l = (a_l + t_l) / 2), type-II Anderson, S^(k+1); returns the stop test."""
        d, n = self.dim, self.n
        T = S.reshape(n, d)
        X = 0.5 * (A + T)
        m = np.add.reduce(A, axis=0) / n  # row after row in id order: the same bits on every copy
        G = (RELAY_RELAX * (m - X)).ravel()
        F = S + G
        g = G * self._w
        res = math.sqrt(float(_pairwise_sum((g * g)[:, None])[0]))
        if self._fresh >= self.delay and res > RELAY_SAFEGUARD * self._best:  # (S^j formed after the last restart)
            self._forget()
        self._best = min(self._best, res)
        self._fresh = min(self._fresh + 1, self.delay)
        self._push(S, F, g)
        self._S[self._lround + 1] = self._extrapolate(F) if len(self._dg) else F
        # stop test on the fleet's residual: the x's spread around their mean, the mean's move
        mean = np.add.reduce(X, axis=0) / n
        rows = np.vstack([X] if self._prev_mean is None else [X, self._prev_mean[None, :]])
        gaps = relative_gaps(mean, rows)
        self.residual = max(float(np.max(gaps[:n])), 0.0 if self._prev_mean is None else float(gaps[-1]))
        self._prev_mean = mean
        self._residuals = (self._residuals + [self.residual])[-self._kept:]
        # margin x the estimate (window maxima), held `hold` rounds in a row, for each test of
        # `relay_stop_tests`: a delayed Anderson can sit on a plateau where the fleet agrees and barely
        # moves, the residual ~70x below the error (measured: 8-ring seed 2 of the old design, error
        # 1.1e-3 for 600 rounds at residual 1.6e-5), where isolated spikes in the older window fake a fast
        # rate: each hold is 1.7x the longest false streak traced (benchmarks/results/rounds-stop-relay.md)
        self._held = relay_stop_held(self._held, self._residuals, self._tests, self.params.tol)
        if self._endgame is not None:  # the end-game's start signal: steps in a row on one piece each
            W = step_normals(self._pdiag, self._P, X, T)
            steady = (self._pieces is not None and self._lround + 1 - self.delay > 1
                      and not bool(piece_changed(*self._pieces, X, W, soft=not self._endgame.hard).any()))
            self._quiet = self._quiet + 1 if steady else 0
            self._pieces = (X, W)
        return relay_stop_passed(self._held, self._tests)

    # -- Anderson -------------------------------------------------------------------------------
    def _forget(self) -> None:
        self._hist_F: list[np.ndarray] = []
        self._hist_g: list[np.ndarray] = []
        self._dg = np.zeros((0, 0))
        self._df = np.zeros((0, 0))
        self._gram = np.zeros((0, 0))
        self._best = math.inf
        self._fresh = 0  # the next D - 1 steps evaluate points formed before this restart: they restart nothing

    def _push(self, S: np.ndarray, F: np.ndarray, g: np.ndarray) -> None:
        """Add the pair (S, F) (weighted residual g): a row of differences and its Gram row."""
        if self._hist_g:
            m = len(self._dg)
            dg = g - self._hist_g[-1]
            dgs = np.vstack([self._dg, dg[None, :]]) if m else dg[None, :]
            dfs = np.vstack([self._df, (F - self._hist_F[-1])[None, :]]) if m else (F - self._hist_F[-1])[None, :]
            row = _pairwise_sum(np.ascontiguousarray((dgs * dg).T))  # dg_i . dg, exactly rounded
            gram = np.empty((m + 1, m + 1))
            gram[:m, :m] = self._gram
            gram[m, :] = gram[:, m] = row
            self._dg, self._df, self._gram = dgs, dfs, gram
            if m + 1 > self._memory:
                self._dg, self._df = self._dg[1:], self._df[1:]
                self._gram = self._gram[1:, 1:].copy()
        self._hist_g = (self._hist_g + [g])[-2:]
        self._hist_F = (self._hist_F + [F])[-2:]

    def _extrapolate(self, F: np.ndarray) -> np.ndarray:
        """F minus the combination of past steps that best cancels the residual (regularised)."""
        m = len(self._dg)
        rhs = _pairwise_sum(np.ascontiguousarray((self._dg * self._hist_g[-1]).T))
        H = self._gram.copy()
        scale = math.fsum(np.diag(H).tolist()) / m
        H[np.diag_indices(m)] += RELAY_REG * max(scale, 1e-300)
        try:
            coef = _solve_spd(H, rhs)
        except np.linalg.LinAlgError:
            return F
        terms = np.empty((m + 1, len(F)))
        terms[0] = F
        np.multiply(coef[:, None], self._df, out=terms[1:])
        return np.subtract.reduce(terms, axis=0)

    # -- internals ------------------------------------------------------------------------------
    def _solve(self, t: np.ndarray, guess: np.ndarray | None = None) -> np.ndarray:
        """The local step at centre t; ``guess`` (this robot's last x) lets the exact warm-started
        KKT solve answer (agents/problem.py `_WarmKKT`), piqp when it does not certify."""
        sol = self._qp.solve(-self._P * t, guess)
        return np.append(sol.x, sol.gamma)

    def _prune(self, oldest: int) -> None:
        """Keep rounds >= oldest (the next step reads round oldest + 1; the frames read newer)."""
        for held in self._a.values():
            for r in [r for r in held if r < oldest]:
                if r != 0:
                    del held[r]
        for r in [r for r in self._S if r < oldest and r != 0]:
            del self._S[r]

    def _forget_edge(self, j: int) -> None:
        """A neighbour died for good: the relay cannot continue exactly (see the module)."""
        self._broken = (f"robot {j} died: the relay hub cannot drop a robot consistently "
                        "(run the edge form, params relay = false, to continue with the survivors)")

    def status(self) -> dict[str, Any]:
        return {**super().status(), "error_estimate": self.estimate()}

    def estimate(self) -> float:
        """The stop tests' smallest margin x estimate (what the status shows against tol)."""
        return min(margin * error_estimate(self._residuals, window=w) for w, margin, _ in self._tests)

    # -- checkpoint -----------------------------------------------------------------------------
    def _save_state(self) -> dict[str, Any]:
        return {
            "S": [[r, to_bytes(s)] for r, s in sorted(self._S.items())],
            "a": [[l, r, to_bytes(a)] for l, held in sorted(self._a.items()) for r, a in sorted(held.items())],
            "hist_F": [to_bytes(f) for f in self._hist_F],
            "hist_g": [to_bytes(g) for g in self._hist_g],
            "dg": [to_bytes(r) for r in self._dg],
            "df": [to_bytes(r) for r in self._df],
            "gram": [to_bytes(r) for r in self._gram],
            "best": self._best,
            "fresh": self._fresh,
            "residuals": list(self._residuals),
            "held": list(self._held),
            "prev_mean": to_bytes(self._prev_mean),
            "frame": to_bytes(self._frame),
            "prev_frame": to_bytes(self._prev_frame),
            "broken": self._broken,
            "token": self._token,
            "certificate": None if self._certificate is None else self._certificate.as_list(),
            "fleet_bound": self._fleet_bound,
            "endgame": None if self._endgame is None else self._endgame_state(),
        }

    def _endgame_state(self) -> dict[str, Any]:
        """The paused end-game's part of a checkpoint (`_save_state`)."""
        eg, red = self._endgame, self._reduce
        assert eg is not None and red is not None
        pieces = self._pieces
        return {
            "mode": self._mode, "paused": self._paused, "next_try": self._next_try, "quiet": self._quiet,
            "pieces": None if pieces is None else [to_bytes(pieces[0].ravel()), to_bytes(pieces[1].ravel())],
            "attempt_base": self._attempt_base, "attempt_steps": self._attempt_steps, "attempts": self._attempts,
            "attempt_v": to_bytes(self._attempt_v), "attempt_lam": to_bytes(self._attempt_lam),
            "reduce_frame": to_bytes(self._reduce_frame), "solver": eg.state(), "reduce": red.save(),
        }

    def _load_state(self, state: dict[str, Any]) -> None:
        self._S = {int(r): from_bytes(s) for r, s in state["S"]}
        self._a = {l: {} for l in self.ids}
        for l, r, a in state["a"]:
            self._a[int(l)][int(r)] = from_bytes(a)
        self._hist_F = [from_bytes(f) for f in state["hist_F"]]
        self._hist_g = [from_bytes(g) for g in state["hist_g"]]
        rows = lambda key: np.array([from_bytes(r) for r in state[key]]) if state[key] else np.zeros((0, 0))  # noqa: E731
        self._dg, self._df, self._gram = rows("dg"), rows("df"), rows("gram")
        self._best = float(state["best"])
        self._fresh = int(state["fresh"])
        self._residuals = [float(r) for r in state["residuals"]]
        held = state["held"]  # a list per stop test; one int (main's test) before branch relaystop, whose
        # count is main's test's only: the others start afresh (a later stop, never an earlier one)
        self._held = (tuple(int(h) for h in held) if isinstance(held, list)
                      else (int(held),) + (0,) * (len(self._tests) - 1))
        self._prev_mean = from_bytes(state["prev_mean"])
        self._frame = from_bytes(state["frame"])
        self._prev_frame = from_bytes(state["prev_frame"])
        self._broken = state["broken"]
        self._token = bytes(state["token"])
        cert = state.get("certificate")
        self._certificate = None if cert is None else Certificate.from_list([float(c) for c in cert])
        self._fleet_bound = float(state.get("fleet_bound", math.inf))
        eg, red, saved = self._endgame, self._reduce, state["endgame"]
        if eg is not None and red is not None:
            self._mode, self._paused = saved["mode"], int(saved["paused"])
            self._next_try, self._quiet = int(saved["next_try"]), int(saved["quiet"])
            pieces = saved["pieces"]
            shape = (self.n, self.dim)
            self._pieces = None if pieces is None else (from_bytes(pieces[0]).reshape(shape),
                                                        from_bytes(pieces[1]).reshape(shape))
            self._attempt_base, self._attempt_steps = int(saved["attempt_base"]), int(saved["attempt_steps"])
            self._attempts = int(saved["attempts"])
            self._attempt_v, self._attempt_lam = from_bytes(saved["attempt_v"]), from_bytes(saved["attempt_lam"])
            self._reduce_frame = from_bytes(saved["reduce_frame"])
            eg.load(saved["solver"])
            red.load(saved["reduce"])
            if self._mode != "admm":  # the attempt's fresh guess (its end) reads the start step's multipliers
                self._qp.multipliers = self._attempt_lam
