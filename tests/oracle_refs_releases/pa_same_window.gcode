; kestimator test: SET_PRESSURE_ADVANCE that keeps the scan window (only ADVANCE changes),
; with moves queued, in the flushed state (after G4 and M400) and before the first move.
; Klipper before c84d78f3f (v0.12.0-262) and Kalico flush step generation at every one;
; from there to 542694350 its look-ahead callback with nothing queued is
; get_last_move_time; today's Klipper moves no time at either
G90
M83
SET_PRESSURE_ADVANCE ADVANCE=0.04
SET_PRESSURE_ADVANCE ADVANCE=0.05
;LAYER:1
G1 X20 Y0 E1 F6000
G1 X40 Y5 E1
SET_PRESSURE_ADVANCE ADVANCE=0.06
G1 X60 Y5 E1
G1 X80 Y0 E1
;LAYER:2
G4 P100
SET_PRESSURE_ADVANCE ADVANCE=0.03
G1 X80 Y30 E1 F9000
G1 X50 Y30 E1
;LAYER:3
M400
SET_PRESSURE_ADVANCE ADVANCE=0.07
G1 X20 Y30 E1
G1 X20 Y60 E1
SET_PRESSURE_ADVANCE ADVANCE=0.02
G1 X0 Y60 E1
;LAYER:4
SET_PRESSURE_ADVANCE ADVANCE=0.05 SMOOTH_TIME=0.04
G1 X0 Y0 E1 F12000
G1 X30 Y0 E0.5
