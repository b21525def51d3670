#!/bin/sh
# Synthesis reports with yosys: the glove core on the LFE5U-12F (ECP5) and a 4x4 fingertip
# variant on the iCE40 (thesis 4.6). Writes hdl/tactile/build/*.log; run from anywhere.
set -e
cd "$(dirname "$0")"
mkdir -p build
SRC="tactile_core.v tactile_packer.v tactile_regs.v tactile_cmd.v uart.v crc32.v"
yosys -q -l build/ecp5.log -p "read_verilog $SRC; chparam -set NTX 16 -set NRX 16 tactile_core; synth_ecp5 -top tactile_core; stat" >/dev/null
yosys -q -l build/ice40.log -p "read_verilog $SRC; chparam -set NTX 4 -set NRX 4 tactile_core; synth_ice40 -top tactile_core; stat" >/dev/null
grep -A40 "Printing statistics" build/ecp5.log | grep -E "LUT4|TRELLIS_FF|FD1S3|MULT18|DP16KD|PDPW16KD|CCU2C|cells" | sed 's/^/ecp5 /'
grep -A40 "Printing statistics" build/ice40.log | grep -E "SB_LUT4|SB_DFF|SB_RAM|SB_CARRY|cells" | sed 's/^/ice40 /'
