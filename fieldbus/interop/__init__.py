"""Vendor device descriptions to drive maps: EtherCAT ESI (:mod:`.esi`) and CANopen EDS/DCF (:mod:`.eds`)."""
