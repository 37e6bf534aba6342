#!/bin/sh
# Regenerate the reference JSONs of klipper-<release>/ with the oracle pointed at that Klipper.
# usage: ORACLE_PYTHON=... sh tests/oracle_refs_releases/make_refs.sh <release> <built tree>
#   release: v0.12.0 or v0.13.0 (klipper-<release>/), or kalico-v2026.07.00; the tree built as
#   .ci/klipper-setup builds 84104bbbd, from ../shared/upstream/klipper-<release>.tar.gz (those
#   tarballs have no lib/kconfiglib: copy the 84104bbbd tree's, only `make olddefconfig` uses
#   it) or ../shared/upstream/kalico-v2026.07.00.tar.gz (ORACLE_PYTHON then a venv with its
#   scripts/klippy-requirements.txt)
set -eu
RELEASE=$1
TREE=$2
MODE=${3:-}
HERE=$(cd "$(dirname "$0")" && pwd)
ORACLE=${ORACLE:-$HERE/../../../shared/tools/oracle/oracle.py}
CORPUS=${CORPUS:-$HERE/../../../shared/corpus}
case $RELEASE in
    kalico-*) DIR=$HERE/$RELEASE ;;
    *) DIR=$HERE/klipper-$RELEASE ;;
esac
[ "$MODE" != heldout ] || DIR=$HERE/heldout/$(basename "$DIR")
case $RELEASE in
    v0.12.0) LABEL="Klipper v0.12.0 (0d67d9c45d2d, 2023-11-10; ../shared/upstream/klipper-v0.12.0.tar.gz), klippy batch mode" ;;
    v0.13.0) LABEL="Klipper v0.13.0 (61c0c8d2ef40, 2025-04-11; ../shared/upstream/klipper-v0.13.0.tar.gz), klippy batch mode" ;;
    84104bbbd) LABEL="Klipper 84104bbbd (v0.13.0-730, 2026-08), klippy batch mode" ;;
    kalico-v2026.07.00) LABEL="Kalico v2026.07.00 (30c65e09de06, 2026-07; ../shared/upstream/kalico-v2026.07.00.tar.gz), klippy batch mode" ;;
    *) echo "make_refs.sh: unknown release $RELEASE" >&2; exit 2 ;;
esac
# make_ref FOLDER GCODE: FOLDER/<name>.json, the oracle run with FOLDER/printer.cfg.
make_ref() {
    folder=$1
    gcode=$2
    name=$(basename "$gcode" .gcode)
    # kestimator's own files are beside the references, the rest the corpus's
    src=$CORPUS/$gcode
    [ -e "$src" ] || src=$HERE/$gcode
    python3 "$ORACLE" "$src" --cfg "$folder/printer.cfg" --klipper "$TREE" \
        --python "$ORACLE_PYTHON" --mark-every 0 --reference > "$folder/$name.json.tmp"
    # The harness labels its output with the Klipper it was written for: say which one ran.
    python3 - "$folder/$name.json.tmp" "$gcode" "$LABEL" <<'PY'
import json, sys
path, gcode, label = sys.argv[1:]
ref = json.load(open(path))
ref["file"], ref["config"], ref["klipper"] = gcode, "printer.cfg", label
with open(path, "w") as out:
    json.dump(ref, out, indent=1)
    out.write("\n")
PY
    mv "$folder/$name.json.tmp" "$folder/$name.json"
}

if [ "$MODE" = heldout ]; then
    # Files and configs never used to develop or tune the release rules (README.md, "Held-out check"):
    # slicers other than the six files' above, with acceleration changes, arcs, a
    # pressure-advance change and firmware retraction, and the one other file with
    # SET_VELOCITY_LIMIT; each config folder's printer.cfg written with this release's own
    # options.
    for config in "$DIR"/*/; do
        for gcode in gcode/superslicer/cancelobj_ss2.3.56_arcwelder.gcode \
            gcode/superslicer/cancelobj_ss2.4_inverted_pyramid.gcode \
            gcode/icesl/cancelobj_icesl_2021-09.gcode \
            gcode/cura/cura413_voron250_torus_relE_fwretract.gcode \
            gcode/ideamaker/cancelobj_ideamaker4.2.0.gcode \
            gcode/kirimoto/cancelobj_kirimoto3.0.gcode \
            gcode/orcaslicer/helixscreen_stand_orca2.3.1_klipper.gcode; do
            make_ref "${config%/}" "$gcode"
        done
    done
    exit 0
fi
[ "$RELEASE" != 84104bbbd ] || { echo "make_refs.sh: 84104bbbd's are ../oracle_refs" >&2; exit 2; }
NUT=gcode/prusaslicer/ps25_nut_accelA_small.gcode
ACCELCTL=gcode/orcaslicer/accelctl_orca1.5.0_klipper_m204.gcode
for gcode in "$NUT" "$ACCELCTL" \
    gcode/orcaslicer/helixscreen_xyzcube_orca2.3.1_klipper.gcode \
    gcode/orcaslicer/helixscreen_calicat_orca2.3.1_klipper.gcode \
    gcode/slic3r/slic3r130_torus_x3_accel.gcode \
    flush_junctions.gcode pa_same_window.gcode lookahead_peak.gcode motor_off.gcode \
    heater_first.gcode; do
    make_ref "$DIR" "$gcode"
done
# fan/printer.cfg: this release's with a [fan]
make_ref "$DIR/fan" fan_first.gcode
case $RELEASE in
    kalico-*)
        # What only Kalico has: its commands, and its limited_* kinematics (each folder's
        # printer.cfg is the corpus's with that kinematics and its per-axis limits).
        make_ref "$DIR" kalico_rules.gcode
        for kinematics in limited_cartesian limited_corexy limited_corexz; do
            for gcode in "$NUT" "$ACCELCTL" kinematics_limit.gcode; do
                make_ref "$DIR/$kinematics" "$gcode"
            done
        done ;;
esac
