; kestimator test: a fan set with nothing queued (extras/fan.py set_speed_from_command's
; look-ahead callback: get_last_move_time) after a homing and after M400: with
; min_restart_time (v0.13.0, Kalico) motion restarts kin_flush_delay after the flush
G90
M83
M107
;LAYER:1
G28
M106 S255
G1 X20 Y20 F6000
;LAYER:2
M400
M106 S128
G1 X40 Y20 E1 F3000
;LAYER:3
G4 P10
M107
G1 X5 F6000
