#!/bin/sh
# Regenerate the reference JSONs of this folder with the oracle (mainline Klipper 84104bbbd).
# usage: ORACLE_KLIPPER=... ORACLE_PYTHON=... sh tests/oracle_refs/make_refs.sh
# Each line of RUNS: <config dir> <G-code: corpus-relative or snippets/...>
set -u
HERE=$(cd "$(dirname "$0")" && pwd)
ORACLE=${ORACLE:-$HERE/../../../shared/tools/oracle/oracle.py}
CORPUS=${CORPUS:-$HERE/../../../shared/corpus/gcode}
while read -r cfg gcode; do
    case "$gcode" in
        snippets/*) src=$HERE/$gcode ;;
        *) src=$CORPUS/$gcode ;;
    esac
    name=$(basename "$gcode" .gcode)
    out=$HERE/$cfg/$name.json
    if python3 "$ORACLE" "$src" --cfg "$HERE/$cfg/printer.cfg" --mark-every 0 --reference > "$out.tmp"; then
        mv "$out.tmp" "$out"
    else
        # Klipper stopped the print: keep the full analysis (errors with their source line)
        python3 "$ORACLE" "$src" --cfg "$HERE/$cfg/printer.cfg" --mark-every 0 > "$out.tmp"
        mv "$out.tmp" "$HERE/$cfg/$name.errors.json"
        rm -f "$out"
    fi
done <<'RUNS'
corexz cura/cura413_ender3_nut_small.gcode
corexz slic3r/cancelobj_slic3r1.3.1dev.gcode
corexz snippets/home_then_move.gcode
corexz snippets/z_moves.gcode
corexz snippets/out_of_range_x.gcode
corexz snippets/motors_off.gcode
corexz snippets/dwell_then_layer.gcode
corexz snippets/motors_off_g28.gcode
corexz snippets/kinematic_position.gcode
corexz_force_move snippets/kinematic_position.gcode
corexz_force_move snippets/kinematic_position_clear.gcode
corexy_maxend cura/cura413_ender3_nut_small.gcode
corexy_maxend snippets/home_then_move.gcode
corexy_probe snippets/home_then_move.gcode
corexy_probe snippets/z_moves.gcode
corexy_probe snippets/home_then_z.gcode
corexy_eddy snippets/home_then_move.gcode
corexy_eddy snippets/z_moves.gcode
corexy_eddy snippets/home_then_z.gcode
delta orcaslicer/helixscreen_xyzcube_orca2.3.1_klipper.gcode
delta snippets/home_then_move.gcode
delta snippets/z_moves.gcode
delta snippets/delta_radius.gcode
delta snippets/delta_out_of_range.gcode
delta snippets/motors_off.gcode
delta snippets/motors_off_g28.gcode
delta snippets/delta_home_xy.gcode
delta snippets/delta_lower_xy.gcode
delta_mini snippets/delta_home_xy.gcode
delta_mini snippets/delta_lower_xy.gcode
delta_tight orcaslicer/helixscreen_xyzcube_orca2.3.1_klipper.gcode
polar slic3r/cancelobj_slic3r1.3.1dev.gcode
polar snippets/polar_center.gcode
polar snippets/polar_out_of_range.gcode
winch snippets/home_then_move.gcode
winch snippets/z_moves.gcode
none snippets/home_then_move.gcode
none snippets/z_moves.gcode
generic_cartesian cura/cura413_ender3_nut_small.gcode
generic_cartesian snippets/home_then_move.gcode
generic_cartesian snippets/z_moves.gcode
generic_cartesian snippets/out_of_range_x.gcode
deltesian snippets/deltesian_moves.gcode
deltesian snippets/deltesian_slow_x.gcode
rotary_delta snippets/rotary_moves.gcode
rotary_delta snippets/rotary_out.gcode
rotary_delta snippets/delta_home_xy.gcode
rotary_delta snippets/delta_lower_xy.gcode
safe_z_home cura/cura413_ender3_nut_small.gcode
safe_z_home snippets/safe_z_home.gcode
safe_z_home_previous cura/cura413_ender3_nut_small.gcode
safe_z_home_previous snippets/safe_z_home.gcode
cartesian_idex cura/cura413_ender3_nut_small.gcode
cartesian_idex snippets/out_of_range_x.gcode
RUNS
