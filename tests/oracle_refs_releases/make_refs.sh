#!/bin/sh
# Regenerate the reference JSONs of klipper-v0.12.0/ with the oracle pointed at Klipper v0.12.0.
# usage: KLIPPER_V0_12=<built v0.12.0 tree> ORACLE_PYTHON=... sh tests/oracle_refs_releases/make_refs.sh
# (the tree built as .ci/klipper-setup builds 84104bbbd, from ../shared/upstream/klipper-v0.12.0.tar.gz;
# that tarball has no lib/kconfiglib: copy the 84104bbbd tree's, only `make olddefconfig` uses it)
set -eu
HERE=$(cd "$(dirname "$0")" && pwd)
ORACLE=${ORACLE:-$HERE/../../../shared/tools/oracle/oracle.py}
CORPUS=${CORPUS:-$HERE/../../../shared/corpus}
DIR=$HERE/klipper-v0.12.0
for gcode in \
    gcode/prusaslicer/ps25_nut_accelA_small.gcode \
    gcode/orcaslicer/accelctl_orca1.5.0_klipper_m204.gcode \
    gcode/orcaslicer/helixscreen_xyzcube_orca2.3.1_klipper.gcode \
    gcode/orcaslicer/helixscreen_calicat_orca2.3.1_klipper.gcode \
    gcode/slic3r/slic3r130_torus_x3_accel.gcode \
    flush_junctions.gcode; do
    name=$(basename "$gcode" .gcode)
    # flush_junctions.gcode is kestimator's own (beside the references), the rest the corpus's
    src=$CORPUS/$gcode
    [ -e "$src" ] || src=$DIR/$gcode
    python3 "$ORACLE" "$src" --cfg "$DIR/printer.cfg" --klipper "$KLIPPER_V0_12" \
        --python "$ORACLE_PYTHON" --mark-every 0 --reference > "$DIR/$name.json.tmp"
    # The harness labels its output with the Klipper it was written for: say which one ran.
    python3 - "$DIR/$name.json.tmp" "$gcode" <<'PY'
import json, sys
path, gcode = sys.argv[1:]
ref = json.load(open(path))
ref["file"], ref["config"] = gcode, "printer.cfg"
ref["klipper"] = ("Klipper v0.12.0 (0d67d9c45d2d, 2023-11-10; ../shared/upstream/"
                  "klipper-v0.12.0.tar.gz), klippy batch mode")
with open(path, "w") as out:
    json.dump(ref, out, indent=1)
    out.write("\n")
PY
    mv "$DIR/$name.json.tmp" "$DIR/$name.json"
done
