; G28 with [safe_z_home]: Z is homed at home_xy_position, then lifted to z_hop; with
; move_to_previous X and Y go back to where homing them left them. The moves after each
; G28 start from there.
G90
M83
G1 X5 Y5 Z1 F6000
G28
;LAYER_CHANGE
G1 X10 Y10 Z2 F12000
G1 X20 Y4 F12000
G1 E1 F1200
G1 Z15 F600
G28 X
;LAYER_CHANGE
G1 X30 Y30 Z12 F9000
G28 Z
;LAYER_CHANGE
G1 X40 Y40 Z3 F9000
G28 Y Z
;LAYER_CHANGE
G1 X50 Y20 Z4 F9000
G1 X60 F9000
