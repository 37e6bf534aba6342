; a layer marker right after a full stop starts after the dwell (Klipper's print_time there)
G90
G1 X10 Y10 Z1 F6000
G4 P500
;LAYER_CHANGE
G1 X20 F6000
G1 X30 Y5 F6000
G4 P250
M400
;LAYER_CHANGE
G1 X10 F6000
;LAYER_CHANGE
G1 X12 F6000
