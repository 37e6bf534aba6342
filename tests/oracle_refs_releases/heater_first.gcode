; kestimator test: a heater set with nothing queued (extras/heaters.py set_temperature's
; look-ahead callback: get_last_move_time) before the first move, after a homing and after
; M400: with min_restart_time (v0.12.0-69 to v0.13.0-237, Kalico) it restarts motion
; kin_flush_delay after the flush; v0.12.0 and today's Klipper move no time there
G90
M83
M140 S43
;LAYER:1
G28
;LAYER:2
M190 S43
G1 X20 Y20 F6000
;LAYER:3
M104 S195
M109 S195
G1 X40 Y20 E1 F3000
;LAYER:4
M400
M104 S200
G28 X
G1 X10 Y10 F6000
;LAYER:5
SET_HEATER_TEMPERATURE HEATER=heater_bed TARGET=50
G1 X5 F6000
