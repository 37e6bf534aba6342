; After G28 and a move down, XY moves inside the slow-down radius that do not move Z pass
; check_move's early return; the one that leaves it is checked (and slowed) again.
G90
M83
G28
;LAYER_CHANGE
G1 Z50 F600
G1 X1 Y1 F6000
G1 Y-3 F6000
G1 X-2 F6000
G1 X2 Y2 E0.5 F3000
;LAYER_CHANGE
G1 X7 Y0 F6000
G1 X0 Y-3 F6000
G1 Y-3 Z40 F6000
G1 X3 F6000
G28
;LAYER_CHANGE
G1 Z20 F600
G1 X-3 Y-3 F6000
