"""Writes the complex test outlines of issue 15 (CSV, header x,y, one vertex a row).

Each is built from boxes, strokes and discs with shapely and rounded to 1e-4 of its unit, so the
files are the data (this script only says how they were made):

- letter_e.csv     (m)  an E: three arms, two notches 0.7 wide and 2.1 deep
- digit_3.csv      (m)  a 3 drawn with a 0.55-wide stroke: two deep concavities on its left
- wrench_mm.csv    (mm) an open-end wrench: a 210 mm handle, a jaw with a 32 mm slot
- gear_mm.csv      (mm) an 8-tooth gear: teeth 14 mm wide, 18 mm long, gaps ~25 mm at the rim
- fork_mm.csv      (mm) a fork of a machine part: three tines 40 mm wide, two slots 30 mm wide

The held-out set (issue 15, committed before any sigma rule was evaluated on it; nothing in the
rules may be tuned on these):

- letter_k.csv     (m)  a K: a V notch between two 0.72-wide diagonal arms
- letter_m.csv     (m)  an M: two 0.7 stems, a 0.72-wide V; two V notches on top, one deep slot below
- digit_2.csv      (m)  a 2 drawn with a 0.6-wide stroke: a hook over a concavity open to the left
- key_mm.csv       (mm) a key: a 48 mm bow, an 18 mm blade with three V cuts 12 mm wide, 7 mm deep
- comb_mm.csv      (mm) a comb: six teeth 20 mm wide, 73 mm long, slots 20 mm wide
- tslot_mm.csv     (mm) a 40 x 40 T-slot extrusion profile: four 8.2 mm slot mouths, each widening
                         to a 13 mm cavity no LiDAR ray reaches
- clamp_mm.csv     (mm) a C-clamp frame: 24 mm arms, a 112 mm deep throat, jaw pads narrowing it

The second held-out set (branch outlines2, committed before any rule was run on it: for the next
rule, evaluated once; nothing may be tuned on these either):

- letter_f.csv     (m)  an F: a 0.7 stem, two arms, a 0.8-wide notch between them, open below
- letter_h.csv     (m)  an H: two 0.7 stems joined by a 0.6 bar, deep notches above and below
- digit_7.csv      (m)  a 7: a 0.6 bar on top, a 0.5-wide diagonal stroke (a thin part)
- hook_mm.csv      (mm) a lifting hook: a 24 mm stroke, a shank into a 240-degree arc (radius 42), ~40 mm mouth
- saw_mm.csv       (mm) a saw blade: 200 x 40 mm, eight V teeth 20 mm wide, 14 mm deep
- slotted_mm.csv   (mm) an L bracket (20 mm legs) with a 6 mm slot 50 mm deep cut into its long leg

The third held-out set (branch sigma5, in heldout3/; committed after the sigma5 rule was frozen and
before any rule or SVC ran on it; evaluated once):

- letter_s.csv       (m)  an S drawn with a 0.6-wide stroke: two concavities, open right above, left below
- digit_4.csv        (m)  an open 4: a 0.6 stem, a 0.56-wide diagonal arm, a crossbar; a V notch open above
- digit_5.csv        (m)  a 5: a top bar, a short stem, a 0.6-wide bowl open to the left
- caliper_mm.csv     (mm) a caliper: a 16 mm beam, two jaws 10 mm wide, 6 mm apart at the tips, 26 mm at the beam
- tuning_fork_mm.csv (mm) a tuning fork: two 10 mm tines, a 14 mm slot 110 mm deep, a 10 mm stem
- bolt_mm.csv        (mm) a bolt: a 30 mm head, a 16 mm shank with 12 thread notches 5 mm wide, 3.5 mm deep
                          on each side

The fourth held-out set (issue 15, branch heldout4, in heldout4/; committed before any rule or SVC ran on it,
for the lead's one evaluation of the next model; nothing may be tuned on these). No closed holes: an outline
file is one ring, and a LiDAR outside could not see a closed hole anyway; the cavities below open to the
outside through a mouth, so rays can reach them:

- letter_w.csv           (m)  a W drawn with a 0.6-wide stroke: two V notches 2.9 deep from above (1.6 wide at
                              the top), one 1.8 deep from below; the middle apex a mitred spike
- letter_x.csv           (m)  an X of two 0.64-wide strokes: four V notches 1.1 to 1.4 deep
- digit_6.csv            (m)  a 6 with a 0.56-wide stroke: a hook over a concavity open to the right, the bowl's
                              counter (radius 0.67) opening into it through a 0.5-wide stencil gap
- pliers_mm.csv          (mm) pliers: a 17 mm pivot disc, 20 mm handles diverging into a 64 mm-wide narrow wedge,
                              jaws 9 mm thick at the tips (thinner than two default offsets: the robot facing them
                              keeps 34 of its 40 points) with a V slot 6 mm wide at the tips, 60 mm deep
- castellated_nut_mm.csv (mm) a castellated nut seen from above, 60 mm across flats: six slots 7 mm wide, 18 mm
                              deep from the flats (the bore omitted: no closed holes)
- circlip_mm.csv         (mm) an external circlip: a 96 mm ring, band 9 to 13 mm, two lugs 18 mm wide beside an
                              18 mm mouth into the ring's 74 mm cavity

The fifth held-out set (issue 15, branch heldout5, in heldout5/; committed before any fleet, rule, SVC or
emulation ran on it, for the lead's one evaluation at the end of the 2026-11-24 session; nothing may be tuned on
these). New kinds next to the 30 above: two opposite acute wedges (digit_7 has one), a lopsided V over a
descender hook, a wound spiral, fins below two offsets (comb_mm's teeth are 20 mm), slots interleaved from both
sides of a thin strip, barbs. One ring each, no closed holes:

- letter_z.csv    (m)  a Z: bars 3.0 x 0.6 at top and bottom, a 0.56-wide diagonal (ends (2.7, 3.7), (0.3, 0.3));
                       two acute wedge notches 2.8 high at the mouth, 2.15 deep, open left under the top bar and
                       right over the bottom bar (a 0.17 ledge where the diagonal leaves each bar)
- letter_y.csv    (m)  a lowercase y: a 0.6-wide short arm from (0.3, 4.3) into a 0.6-wide long arm from (3.0, 4.3)
                       whose descender hooks left and up (round joins), cut to y <= 4: a V notch 1.9 deep from
                       above (apex at (1.83, 2.12)), a concavity open left between the short arm and the hook
- spiral.csv      (m)  an Archimedean spiral stroke 0.5 wide, 1.75 turns, radius 0.35 to 2.1 (1.0 apart a turn), so
                       a 0.5-wide channel (less than two 0.3 offsets) runs 0.75 turns between the turns
- heatsink_mm.csv (mm) an extruded heat sink: a 100 x 12 base, nine fins 4 mm thick (thinner than two 6 mm
                       offsets), 70 mm tall, 8 mm gaps 58 mm deep
- spring_mm.csv   (mm) a flat serpentine spring: an 8 mm strip (thinner than two offsets), seven legs 60 mm long
                       at a 14 mm pitch, round outer bends: six 6 mm slots 60 mm deep, alternately open below and
                       above
- anchor_mm.csv   (mm) a ship's anchor: a 12 mm shank, a 56 x 10 stock, an 18 mm eye (solid), a 10 mm arc of
                       radius 42 (200 to 340 degrees) whose ends carry 18 mm-wide barbed flukes 28 mm long: acute
                       notches under each barb

The sixth held-out set (issue 15, branch heldout6, in heldout6/; committed before any fleet, rule, SVC or
emulation ran on it, for the lead's one evaluation of the next model or rule; nothing may be tuned on these). New
kinds next to the 36 above: a spur jutting into a counter's mouth, two counters behind gaps opening to opposite
sides, tangential (chiral) pockets, asymmetric teeth round a disc, dovetail undercuts, round undercut lobes
stepping out up a taper. One ring each, no closed holes:

- letter_g.csv    (m)  a G: a 0.56-wide stroke along an elliptic arc (semi-axes 1.22 x 1.72 about (1.5, 2.0), 40 to
                       340 degrees, flat ends), a 0.5-wide jaw from the arc's lower end (2.65, 1.41) up to y = 2 and
                       a spur from there left to x = 1.55 (mitred): the counter opens right through a 0.70 mouth
                       above the spur, and a pocket under the spur opens only back into the counter
- digit_8.csv     (m)  an 8 of two rings with 0.55 strokes: above radius 1.0 about (1.5, 3.0), below radius 1.1
                       about (1.5, 1.1), overlapping 0.2 at the waist (notches left and right); the upper counter
                       (radius 0.45) opens right through a 0.45 gap, the lower (radius 0.55) left through a 0.5 gap,
                       both less than two 0.3 offsets
- triskelion.csv  (m)  a triskelion: a hub of radius 0.6 and three 0.6-wide arms (round ends), each along an
                       Archimedean curve from radius 0.4 to 1.95 over 120 degrees, 120 degrees apart: under each arm
                       a wedge pocket 0.95 wide (radially) at its mouth, narrowing to the hub over 120 degrees, whose
                       mouth faces round the object (counterclockwise), not out from it
- ratchet_mm.csv  (mm) a ratchet wheel: twelve asymmetric teeth 14 mm deep, root radius 36 mm, tips at radius 50,
                       each a radial face, a 4-degree land and a straight back to the next tooth's root: gaps 22.5 mm
                       at the rim, one wall radial and one sloping (the bore omitted: no closed holes)
- dovetail_mm.csv (mm) a dovetailed board end: a 120 x 15 board, three tails 40 mm long, 14 mm wide at the board
                       and 28 mm at the end (flanks 9.9 degrees off square), 40 mm apart: two sockets 12 mm wide at
                       the mouth, 26 mm at the base (undercut on both flanks); the end tails overhang a 13 mm ledge
                       by 7 mm
- fir_tree_mm.csv (mm) a turbine blade's fir-tree root: an 80 x 16 platform on a root tapering from 12 mm wide at
                       the bottom to 36 mm under the platform, with three pairs of round lobes 14 mm thick at
                       heights 10, 32, 54 reaching 17, 23, 29 mm from the centre line: round-bottomed notches 8 mm
                       high at the lobe tips, undercut by the lobe above, and an 18 mm notch under the platform

    .venv/bin/python benchmarks/outlines/make_outlines.py
"""

from __future__ import annotations

import math
from pathlib import Path

import numpy as np
import shapely
import shapely.affinity
from shapely.geometry import LineString, Point, Polygon

HERE = Path(__file__).resolve().parent


def letter_e() -> Polygon:
    body = shapely.box(0.0, 0.0, 3.0, 4.0)
    notch = 0.7
    arm = (4.0 - 2 * notch) / 3.0
    for k in (1, 2):
        y0 = k * arm + (k - 1) * notch
        body = body.difference(shapely.box(0.9, y0, 3.01, y0 + notch))
    return body


def digit_3() -> Polygon:
    t1 = np.linspace(math.radians(150), math.radians(-90), 25)
    t2 = np.linspace(math.radians(90), math.radians(-150), 25)
    upper = np.column_stack([1.2 * np.cos(t1), 1.0 + 1.0 * np.sin(t1)])
    lower = np.column_stack([1.35 * np.cos(t2), -1.1 + 1.1 * np.sin(t2)])
    stroke = LineString(np.vstack([upper, lower])).buffer(0.275, quad_segs=4)
    return stroke


def wrench_mm() -> Polygon:
    handle = shapely.box(0.0, -15.0, 210.0, 15.0)
    head = Point(235.0, 0.0).buffer(40.0, quad_segs=16)
    slot = shapely.box(228.0, -16.0, 290.0, 16.0)
    return handle.union(head).difference(slot)


def gear_mm() -> Polygon:
    body = Point(0.0, 0.0).buffer(45.0, quad_segs=24)
    for k in range(8):
        tooth = shapely.box(35.0, -7.0, 63.0, 7.0)
        body = body.union(shapely.affinity.rotate(tooth, 45.0 * k, origin=(0.0, 0.0)))
    return body


def fork_mm() -> Polygon:
    base = shapely.box(0.0, 0.0, 180.0, 60.0)
    tines = [shapely.box(x, 59.0, x + 40.0, 200.0) for x in (0.0, 70.0, 140.0)]
    return shapely.union_all([base, *tines])


def letter_k():
    stem = shapely.box(0.0, 0.0, 0.8, 4.0)
    upper = LineString([(0.7, 1.8), (2.75, 4.0)]).buffer(0.36, cap_style="flat")
    lower = LineString([(1.35, 2.4), (2.85, 0.0)]).buffer(0.36, cap_style="flat")
    return shapely.union_all([stem, upper, lower]).intersection(shapely.box(0.0, 0.0, 3.0, 4.0))


def letter_m():
    stems = [shapely.box(0.0, 0.0, 0.7, 4.0), shapely.box(3.3, 0.0, 4.0, 4.0)]
    v = LineString([(0.35, 3.7), (2.0, 1.3), (3.65, 3.7)]).buffer(0.36, cap_style="flat", join_style="mitre")
    return shapely.union_all([*stems, v]).intersection(shapely.box(0.0, 0.0, 4.0, 4.0))


def digit_2():
    t = np.linspace(math.radians(160), math.radians(-40), 25)
    arc = np.column_stack([1.1 * np.cos(t), 1.0 + 1.0 * np.sin(t)])
    path = np.vstack([arc, [(-1.2, -1.7), (1.3, -1.7)]])
    return LineString(path).buffer(0.3, quad_segs=4, join_style="round")


def key_mm():
    bow = Point(0.0, 0.0).buffer(24.0, quad_segs=16)
    blade = shapely.box(20.0, -9.0, 110.0, 9.0)
    body = bow.union(blade)
    for x in (44.0, 64.0, 84.0):
        body = body.difference(shapely.Polygon([(x, -9.01), (x + 12.0, -9.01), (x + 6.0, -2.0)]))
    return body


def comb_mm():
    spine = shapely.box(0.0, 0.0, 220.0, 28.0)
    teeth = [shapely.box(40.0 * k, 27.0, 40.0 * k + 20.0, 100.0) for k in range(6)]
    return shapely.union_all([spine, *teeth])


def tslot_mm():
    body = shapely.box(-20.0, -20.0, 20.0, 20.0)
    slot = shapely.union_all([shapely.box(-4.1, 15.5, 4.1, 20.01), shapely.box(-6.5, 9.5, 6.5, 15.5)])
    for k in range(4):
        body = body.difference(shapely.affinity.rotate(slot, 90.0 * k, origin=(0.0, 0.0)))
    return body


def clamp_mm():
    outer = shapely.box(0.0, 0.0, 120.0, 160.0)
    inner = shapely.box(24.0, 24.0, 120.01, 136.0)
    pads = [shapely.box(96.0, 23.0, 120.0, 44.0), shapely.box(96.0, 116.0, 120.0, 137.0)]
    return shapely.union_all([outer.difference(inner), *pads])


def letter_f():
    stem = shapely.box(0.0, 0.0, 0.7, 4.0)
    top = shapely.box(0.0, 3.3, 2.6, 4.0)
    mid = shapely.box(0.0, 1.9, 2.0, 2.6)
    return shapely.union_all([stem, top, mid])


def letter_h():
    stems = [shapely.box(0.0, 0.0, 0.7, 4.0), shapely.box(2.3, 0.0, 3.0, 4.0)]
    return shapely.union_all([*stems, shapely.box(0.0, 1.7, 3.0, 2.3)])


def digit_7():
    bar = shapely.box(0.0, 3.4, 2.6, 4.0)
    stroke = LineString([(2.45, 3.5), (0.9, 0.0)]).buffer(0.25, cap_style="flat")
    return shapely.union_all([bar, stroke]).intersection(shapely.box(0.0, 0.0, 2.6, 4.0))


def hook_mm():
    t = np.linspace(math.radians(180), math.radians(420), 40)
    arc = np.column_stack([42.0 * np.cos(t), 42.0 * np.sin(t)])
    shank = np.array([(-42.0, 120.0)])
    return LineString(np.vstack([shank, arc])).buffer(12.0, quad_segs=6, cap_style="round")


def saw_mm():
    body = shapely.box(0.0, 0.0, 200.0, 40.0)
    for k in range(8):
        x = 15.0 + 22.0 * k
        body = body.difference(shapely.Polygon([(x, 40.01), (x + 20.0, 40.01), (x + 10.0, 26.0)]))
    return body


def slotted_mm():
    l_shape = shapely.union_all([shapely.box(0.0, 0.0, 160.0, 20.0), shapely.box(0.0, 0.0, 20.0, 100.0)])
    return l_shape.union(shapely.box(60.0, 0.0, 100.0, 70.0)).difference(shapely.box(77.0, 20.0, 83.0, 70.01))


def letter_s():
    t1 = np.linspace(math.radians(20), math.radians(270), 25)
    t2 = np.linspace(math.radians(90), math.radians(-160), 25)
    upper = np.column_stack([1.1 * np.cos(t1), 1.0 + 1.0 * np.sin(t1)])
    lower = np.column_stack([1.1 * np.cos(t2), -1.0 + 1.0 * np.sin(t2)])
    return LineString(np.vstack([upper, lower])).buffer(0.3, quad_segs=4)


def digit_4():
    stem = shapely.box(1.9, 0.0, 2.5, 4.0)
    arm = LineString([(1.1, 4.0), (0.0, 1.4)]).buffer(0.28, cap_style="flat")
    bar = shapely.box(0.0, 1.1, 3.0, 1.7)
    return shapely.union_all([stem, arm, bar]).intersection(shapely.box(0.0, 0.0, 3.0, 4.0))


def digit_5():
    top = shapely.box(0.2, 3.4, 2.4, 4.0)
    stem = shapely.box(0.2, 2.0, 0.8, 4.0)
    t = np.linspace(math.radians(130), math.radians(-140), 25)
    bowl = LineString(np.column_stack([1.2 + 1.05 * np.cos(t), 1.1 + 1.05 * np.sin(t)])).buffer(0.3, quad_segs=4)
    return shapely.union_all([top, stem, bowl])


def caliper_mm():
    beam = shapely.box(0.0, 0.0, 220.0, 16.0)
    fixed_jaw = shapely.Polygon([(0.0, 0.0), (14.0, 0.0), (14.0, -60.0), (4.0, -60.0), (0.0, -50.0)])
    slider = shapely.box(40.0, -4.0, 90.0, 20.0)
    moving_jaw = shapely.Polygon([(40.0, -4.0), (50.0, -4.0), (30.0, -60.0), (20.0, -60.0)])
    return shapely.union_all([beam, fixed_jaw, slider, moving_jaw])


def tuning_fork_mm():
    stem = shapely.box(-5.0, 0.0, 5.0, 70.0)
    base = Point(0.0, 78.0).buffer(17.0, quad_segs=16)
    tines = [shapely.box(-17.0, 78.0, -7.0, 190.0), shapely.box(7.0, 78.0, 17.0, 190.0)]
    return shapely.union_all([stem, base.difference(shapely.box(-7.0, 80.0, 7.0, 100.0)), *tines]).difference(
        shapely.box(-7.0, 80.0, 7.0, 190.1))


def bolt_mm():
    head = shapely.box(0.0, -15.0, 14.0, 15.0)
    shank = shapely.box(14.0, -8.0, 110.0, 8.0)
    body = head.union(shank)
    for k in range(12):
        x = 40.0 + 5.5 * k
        for y0, tip in ((8.01, 4.5), (-8.01, -4.5)):
            body = body.difference(shapely.Polygon([(x, y0), (x + 5.0, y0), (x + 2.5, tip)]))
    return body


def letter_w() -> Polygon:
    path = [(0.3, 4.0), (1.25, 0.0), (2.2, 2.7), (3.15, 0.0), (4.1, 4.0)]
    stroke = LineString(path).buffer(0.3, cap_style="flat", join_style="mitre", mitre_limit=3.0)
    return stroke.intersection(shapely.box(0.0, 0.0, 4.4, 4.0))


def letter_x() -> Polygon:
    strokes = [LineString([(0.2, 4.2), (2.8, -0.2)]).buffer(0.32, cap_style="flat"),
               LineString([(0.2, -0.2), (2.8, 4.2)]).buffer(0.32, cap_style="flat")]
    return shapely.union_all(strokes).intersection(shapely.box(0.0, 0.0, 3.0, 4.0))


def digit_6() -> Polygon:
    bowl = Point(1.3, 1.25).buffer(1.23, quad_segs=16).difference(Point(1.3, 1.25).buffer(0.67, quad_segs=16))
    gap = shapely.affinity.rotate(shapely.box(1.3, 1.0, 2.8, 1.5), 35.0, origin=(1.3, 1.25))
    t = np.linspace(math.radians(180), math.radians(55), 20)
    spine = np.column_stack([1.95 + 1.6 * np.cos(t), 1.9 + 1.9 * np.sin(t)])
    hook = LineString(np.vstack([[(0.35, 1.25)], spine])).buffer(0.28, quad_segs=4, cap_style="flat")
    return shapely.union_all([bowl.difference(gap), hook]).intersection(shapely.box(0.0, 0.0, 3.0, 4.0))


def pliers_mm() -> Polygon:
    pivot = Point(0.0, 0.0).buffer(17.0, quad_segs=16)
    handles = [LineString([(0.0, s * 6.0), (-60.0, s * 14.0), (-160.0, s * 42.0)]).buffer(10.0, quad_segs=6)
               for s in (1.0, -1.0)]
    jaws = Polygon([(0.0, 18.0), (50.0, 15.0), (72.0, 12.0), (72.0, 3.0), (12.0, 0.0), (72.0, -3.0), (72.0, -12.0),
                    (50.0, -15.0), (0.0, -18.0)])
    return shapely.union_all([pivot, *handles, jaws])


def castellated_nut_mm() -> Polygon:
    corner = 60.0 / math.sqrt(3.0)  # 60 mm across flats
    body = Polygon([(corner * math.cos(math.radians(60 * k)), corner * math.sin(math.radians(60 * k))) for k in range(6)])
    for k in range(6):
        slot = shapely.box(12.0, -3.5, 40.0, 3.5)
        body = body.difference(shapely.affinity.rotate(slot, 30.0 + 60.0 * k, origin=(0.0, 0.0)))
    return body


def circlip_mm() -> Polygon:
    ring = Point(0.0, 0.0).buffer(48.0, quad_segs=24).difference(Point(-2.0, 0.0).buffer(37.0, quad_segs=24))
    lugs = [shapely.box(36.0, 9.0, 62.0, 27.0), shapely.box(36.0, -27.0, 62.0, -9.0)]
    return shapely.union_all([ring, *lugs]).difference(shapely.box(30.0, -9.0, 62.1, 9.0))


def letter_z() -> Polygon:
    bars = [shapely.box(0.0, 0.0, 3.0, 0.6), shapely.box(0.0, 3.4, 3.0, 4.0)]
    stroke = LineString([(2.7, 3.7), (0.3, 0.3)]).buffer(0.28, cap_style="flat")
    return shapely.union_all([*bars, stroke]).intersection(shapely.box(0.0, 0.0, 3.0, 4.0))


def letter_y() -> Polygon:
    short = LineString([(0.3, 4.3), (1.85, 1.45)]).buffer(0.3, cap_style="flat")
    long = LineString([(3.0, 4.3), (1.6, 0.7), (1.1, -0.15), (0.6, -0.45), (0.2, -0.25)]).buffer(
        0.3, quad_segs=4, cap_style="round", join_style="round")
    return shapely.union_all([short, long]).intersection(shapely.box(0.0, -1.0, 3.4, 4.0))


def spiral() -> Polygon:
    t = np.linspace(0.0, 3.5 * math.pi, 90)
    radius = 0.35 + t / (2.0 * math.pi)  # 1.0 apart per turn: a 0.5 stroke, a 0.5 gap
    return LineString(np.column_stack([radius * np.cos(t), radius * np.sin(t)])).buffer(0.25, quad_segs=4)


def heatsink_mm() -> Polygon:
    base = shapely.box(0.0, 0.0, 100.0, 12.0)
    fins = [shapely.box(12.0 * k, 11.0, 12.0 * k + 4.0, 70.0) for k in range(9)]
    return shapely.union_all([base, *fins])


def spring_mm() -> Polygon:
    path = []
    for k in range(7):
        x = 14.0 * k
        path += [(x, 0.0), (x, 60.0)] if k % 2 == 0 else [(x, 60.0), (x, 0.0)]
    return LineString(path).buffer(4.0, quad_segs=6, cap_style="flat", join_style="round")


def anchor_mm() -> Polygon:
    shank = shapely.box(-6.0, 18.0, 6.0, 98.0)
    stock = shapely.box(-28.0, 82.0, 28.0, 92.0)
    eye = Point(0.0, 104.0).buffer(9.0, quad_segs=12)
    t = np.linspace(math.radians(200), math.radians(340), 30)
    arms = LineString(np.column_stack([42.0 * np.cos(t), 60.0 + 42.0 * np.sin(t)])).buffer(5.0, quad_segs=4)
    flukes = []
    for angle in (200.0, 340.0):
        a = math.radians(angle)
        end = np.array([42.0 * math.cos(a), 60.0 + 42.0 * math.sin(a)])
        u = np.array([math.sin(a), -math.cos(a)]) * (1.0 if angle < 270.0 else -1.0)  # along the arm, outward
        n = np.array([-u[1], u[0]])
        flukes.append(Polygon([end - 6.0 * u + 9.0 * n, end + 22.0 * u, end - 6.0 * u - 9.0 * n]))
    return shapely.union_all([shank, stock, eye, arms, *flukes])


def letter_g() -> Polygon:
    t = np.linspace(math.radians(40), math.radians(340), 40)
    arc = np.column_stack([1.5 + 1.22 * np.cos(t), 2.0 + 1.72 * np.sin(t)])
    stroke = LineString(arc).buffer(0.28, quad_segs=4, cap_style="flat")
    end = arc[-1]
    jaw = LineString([end, (end[0], 2.0), (1.55, 2.0)]).buffer(0.25, cap_style="flat", join_style="mitre")
    return shapely.union_all([stroke, jaw]).intersection(shapely.box(0.0, 0.0, 3.0, 4.0))


def digit_8() -> Polygon:
    upper = Point(1.5, 3.0).buffer(1.0, quad_segs=16).difference(Point(1.5, 3.0).buffer(0.45, quad_segs=16))
    lower = Point(1.5, 1.1).buffer(1.1, quad_segs=16).difference(Point(1.5, 1.1).buffer(0.55, quad_segs=16))
    upper = upper.difference(shapely.box(1.5, 2.775, 2.6, 3.225))  # the upper counter's gap, open right
    lower = lower.difference(shapely.box(0.3, 0.85, 1.5, 1.35))  # the lower counter's gap, open left
    return shapely.union_all([upper, lower])


def triskelion() -> Polygon:
    hub = Point(0.0, 0.0).buffer(0.6, quad_segs=16)
    t = np.linspace(0.0, math.radians(120), 30)
    radius = 0.4 + 1.55 * t / t[-1]
    arm = LineString(np.column_stack([radius * np.cos(t), radius * np.sin(t)])).buffer(0.3, quad_segs=4)
    return shapely.union_all([hub, *(shapely.affinity.rotate(arm, 120.0 * k, origin=(0.0, 0.0)) for k in range(3))])


def ratchet_mm() -> Polygon:
    corners = []
    for k in range(12):
        face, land = math.radians(30.0 * k), math.radians(30.0 * k + 4.0)
        corners += [(36.0 * math.cos(face), 36.0 * math.sin(face)), (50.0 * math.cos(face), 50.0 * math.sin(face)),
                    (50.0 * math.cos(land), 50.0 * math.sin(land))]
    return Polygon(corners)


def dovetail_mm() -> Polygon:
    board = shapely.box(0.0, 0.0, 120.0, 15.0)
    # 14 mm wide at the board's face (y = 15), 28 at the end: flanks 7 mm out over 40 mm (and 1 mm into the board)
    tails = [Polygon([(c - 6.825, 14.0), (c + 6.825, 14.0), (c + 14.0, 55.0), (c - 14.0, 55.0)])
             for c in (20.0, 60.0, 100.0)]
    return shapely.union_all([board, *tails])


def fir_tree_mm() -> Polygon:
    root = Polygon([(-6.0, 0.0), (6.0, 0.0), (18.0, 80.0), (-18.0, 80.0)])
    lobes = [LineString([(-w, y), (w, y)]).buffer(7.0, quad_segs=8)
             for w, y in ((10.0, 10.0), (16.0, 32.0), (22.0, 54.0))]
    platform = shapely.box(-40.0, 79.0, 40.0, 95.0)
    return shapely.union_all([root, *lobes, platform])


def write(name: str, polygon: Polygon, digits: int, folder: Path = HERE) -> None:
    polygon = shapely.set_precision(polygon.simplify(10.0 ** -digits), 10.0 ** -digits)
    assert polygon.geom_type == "Polygon" and polygon.is_valid and not polygon.interiors, name
    coords = np.asarray(polygon.exterior.coords)[:-1]
    text = "x,y\n" + "".join(f"{x:.{digits}f},{y:.{digits}f}\n" for x, y in coords)
    folder.mkdir(exist_ok=True)
    (folder / name).write_text(text)


#: (maker, decimals): metres to 1e-4, millimetres to 1e-2; the held-out set from letter_k on, the second from letter_f on
OUTLINES = ((letter_e, 4), (digit_3, 4), (wrench_mm, 2), (gear_mm, 2), (fork_mm, 2),
            (letter_k, 4), (letter_m, 4), (digit_2, 4), (key_mm, 2), (comb_mm, 2), (tslot_mm, 2), (clamp_mm, 2),
            (letter_f, 4), (letter_h, 4), (digit_7, 4), (hook_mm, 2), (saw_mm, 2), (slotted_mm, 2))
#: the third held-out set, in heldout3/: caliper_mm and tuning_fork_mm have parts thinner than two default
#: offsets, so a robot placed by default keeps 22 of its 40 points there (tests/test_world_scale.py asks every
#: outline of this folder for all 40)
HELDOUT3 = ((letter_s, 4), (digit_4, 4), (digit_5, 4), (caliper_mm, 2), (tuning_fork_mm, 2), (bolt_mm, 2))
#: the fourth held-out set, in heldout4/ (pliers_mm: the robot facing its 9 mm jaw tips keeps 34 of 40 points)
HELDOUT4 = ((letter_w, 4), (letter_x, 4), (digit_6, 4), (pliers_mm, 2), (castellated_nut_mm, 2), (circlip_mm, 2))
#: the fifth held-out set, in heldout5/ (points kept: benchmarks/results/autogrid.md, "Held-out 5")
HELDOUT5 = ((letter_z, 4), (letter_y, 4), (spiral, 4), (heatsink_mm, 2), (spring_mm, 2), (anchor_mm, 2))
#: the sixth held-out set, in heldout6/ (pairs kept: benchmarks/results/autogrid.md, "Held-out 6")
HELDOUT6 = ((letter_g, 4), (digit_8, 4), (triskelion, 4), (ratchet_mm, 2), (dovetail_mm, 2), (fir_tree_mm, 2))

if __name__ == "__main__":
    for make, digits in OUTLINES:
        write(f"{make.__name__}.csv", make(), digits)
    for make, digits in HELDOUT3:
        write(f"{make.__name__}.csv", make(), digits, HERE / "heldout3")
    for make, digits in HELDOUT4:
        write(f"{make.__name__}.csv", make(), digits, HERE / "heldout4")
    for make, digits in HELDOUT5:
        write(f"{make.__name__}.csv", make(), digits, HERE / "heldout5")
    for make, digits in HELDOUT6:
        write(f"{make.__name__}.csv", make(), digits, HERE / "heldout6")
