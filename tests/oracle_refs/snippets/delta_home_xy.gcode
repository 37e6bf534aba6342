; After G28 a delta's head is at the top, where the build radius is 0: an XY move there is
; out of range for Klipper (its check_move returns early only for an XY move inside the
; radius its last accepted move allowed, and homing resets that to none).
G90
G28
G1 Y-3 F6000
G1 X2 F6000
