; G28 leaves Z at the probe virtual endstop's position_endstop; a slow Z move shows where
G90
G28
;LAYER_CHANGE
G1 Z10 F300
;LAYER_CHANGE
G1 X20 Y20 F6000
