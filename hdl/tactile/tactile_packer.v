// Frame packer: type, length, header, IMU samples, shared-exponent blocks of the enabled cells, as
// shared/protocols/tactile.py encode_frame (byte-exact; checked against the vectors file). The framer
// (tactile_framer.v) adds sync and CRC; out_last marks the last payload byte.
// Timestamp: a byte stream (least significant byte with ts_first, then one byte a clock), taken at
// the first ts_first after start into r_ts, a shift register that also sends it.
// Frame memory: rd_addr = {excitation line, reception line}, rd_data = {im, re}, 28-bit signed each,
// registered read (one clock). IMU memory: imu_addr = {slot, word}, 16-bit words, registered read; a
// frame carries imu_count samples from slot imu_base on (mod 16), 6 words each.
//
// The datapath handles one 28-bit value at a time. First pass over a block: its peak |v| is kept as
// {a, s} with a = v ^ sign (= |v| - s) and s = sign, compared as one 28-bit key (no negation).
// Exponent: start at e = 0 and shift the peak right (ceil kept as floor + sticky bit) while it
// exceeds 32767, or left while twice it still fits. Second pass: each value is shifted by e - 1 to
// the right (or 1 - e to the left) in the same register and rounded half up: m = (w + 1) >> 1.
module tactile_packer (
    input  wire clk, input wire rst, input wire start,
    input  wire [31:0] seq, input wire [7:0] ts_byte, input wire ts_first,
    input  wire [15:0] tx_mask, input wire [15:0] rx_mask, input wire [7:0] status,
    input  wire [3:0] imu_count, input wire [3:0] imu_base,
    output wire [7:0] rd_addr, input wire [55:0] rd_data,
    output wire [6:0] imu_addr, input wire [15:0] imu_data,
    output reg  [7:0] out_data, output reg out_valid, output reg out_last, input wire out_ready,
    output wire busy
);
    localparam IDLE = 0, COUNT = 1, HEAD = 2, IMU_A = 3, IMU_B = 4, SCAN_A = 5, SCAN_R = 6, SCAN_I = 7,
               NORM = 8, EXPO = 9, EMIT_A = 10, EMIT_L = 11, EMIT_S = 12, EMIT_B = 13;
    reg [3:0] state;
    reg [31:0] r_seq; reg [63:0] r_ts; reg [15:0] r_tx, r_rx; reg [7:0] r_status; reg [3:0] r_n;
    reg [8:0] c, c0;         // cell {k, j}; 256 = past the end; first cell of the block
    reg [3:0] cnt, cnt2;     // cells in this block (<= 8), cells emitted
    reg [10:0] len;          // payload length (counted before the header), then payload bytes left
    reg [4:0] idx;           // header byte
    reg [3:0] tcap;          // timestamp bytes still to take (8: waiting for ts_first)
    reg [3:0] slot; reg [2:0] wrd;  // IMU sample slot, word
    reg hi;                  // high byte of a 16-bit word next
    reg part;                // 0 real, 1 imaginary part
    reg [27:0] R;            // peak, then the value being shifted
    reg ps;                  // sign of the peak, then its sticky bit
    reg nz;                  // block has a nonzero value
    reg signed [4:0] e;      // exponent (-14..13 for 28-bit values)
    reg [4:0] sh, sc;        // |e - 1|: shift per value; shifts left to do
    reg left;                // e <= 0: values shift left
    assign busy = (state != IDLE);
    assign rd_addr = c[7:0];
    assign imu_addr = {slot, wrd};

    wire fire = out_valid && out_ready;
    wire enabled = !c[8] && r_tx[c[7:4]] && r_rx[c[3:0]];
    wire [27:0] re = rd_data[27:0];
    wire [27:0] im = rd_data[55:28];
    wire sgn = part ? im[27] : re[27];
    reg scanning;  // state is SCAN_R or SCAN_I (a flip-flop: the compare path starts at flip-flops)
    wire [27:0] x = (part ? im : re) ^ {28{scanning & sgn}};  // scan: |v| - sign; emit: v
    wire gt = {x[26:0], sgn} > {R[26:0], ps};
    wire hi_nz = |R[26:15];
    wire ones = &R[13:0];
    wire cond_r = hi_nz || (R[14] && ones && ps);   // peak > 32767 x 2^e
    wire cond_l = !hi_nz && !R[14] && !(ones && ps);  // 2 x peak <= 32767 x 2^e
    wire sh_left = (state == NORM) ? !cond_r : left;
    wire [27:0] R_sh = sh_left ? {R[26:0], ps} : {R[27], R[27:1]};
    wire [15:0] m = R[16:1] + {15'd0, R[0]};
    // One adder for the length: +5 (a block's first cell: exponent and 4 bytes) or +4 per enabled
    // cell while counting, -1 per payload byte sent.
    wire [10:0] len_next = len + ((state == COUNT) ? ((cnt[2:0] == 3'd0) ? 11'd5 : 11'd4) : 11'h7FF);
    reg [7:0] len0;  // 18 + 12 n: header and IMU samples
    always @* case (imu_count)
        4'd0: len0 = 8'd18; 4'd1: len0 = 8'd30; 4'd2: len0 = 8'd42; 4'd3: len0 = 8'd54; 4'd4: len0 = 8'd66;
        4'd5: len0 = 8'd78; 4'd6: len0 = 8'd90; 4'd7: len0 = 8'd102; default: len0 = 8'd114;
    endcase
    // Value register: cleared at a block's start, loaded (scan: a bigger peak; emit: the next value) or
    // shifted (exponent search; the value's shift); clear over enable.
    wire r_clr = (state == COUNT && c[8]) || (state == EMIT_A && cnt2 == cnt);
    wire r_load = (scanning && gt) || (state == EMIT_L);
    wire r_shift = (state == NORM && (cond_r || (nz && cond_l))) || (state == EMIT_S && sc != 5'd0);
    always @(posedge clk)
        if (r_clr) R <= 28'd0;
        else if (r_load) R <= x;
        else if (r_shift) R <= R_sh;

    reg [7:0] head;
    always @* case (idx)
        5'd0: head = 8'h01;
        5'd1: head = len[7:0];
        5'd2: head = {5'd0, len[10:8]};
        5'd3: head = r_seq[7:0];
        5'd4: head = r_seq[15:8];
        5'd5: head = r_seq[23:16];
        5'd6: head = r_seq[31:24];
        5'd7, 5'd8, 5'd9, 5'd10, 5'd11, 5'd12, 5'd13, 5'd14: head = r_ts[7:0];
        5'd15: head = r_tx[7:0];
        5'd16: head = r_tx[15:8];
        5'd17: head = r_rx[7:0];
        5'd18: head = r_rx[15:8];
        5'd19: head = r_status;
        default: head = {4'd0, r_n};
    endcase

    // r_ts shifts a byte in while taking the timestamp and a byte out per timestamp byte sent
    wire ts_take = (tcap != 4'd0) && (tcap != 4'd8 || ts_first);
    wire ts_sent = (state == HEAD) && fire && (idx >= 5'd7) && (idx <= 5'd14);
    always @(posedge clk) begin
        if (ts_take || ts_sent) r_ts <= {ts_byte, r_ts[63:8]};
        if (rst) tcap <= 4'd0;
        else if (state == IDLE && start) tcap <= 4'd8;
        else if (ts_take) tcap <= tcap - 1;
    end

    reg [7:0] byte_out;  // the byte the current state sends
    always @* case (state)
        HEAD: byte_out = head;
        IMU_B: byte_out = hi ? imu_data[15:8] : imu_data[7:0];
        EXPO: byte_out = nz ? {{3{e[4]}}, e} : 8'h80;
        default: byte_out = hi ? m[15:8] : m[7:0];
    endcase
    // Sending: the byte is presented (out_valid) in the state's first clock, taken on out_ready.
    always @(posedge clk) begin
        if (rst) begin out_valid <= 1'b0; out_last <= 1'b0; end
        else if (!out_valid && (state == HEAD || state == IMU_B || state == EXPO || state == EMIT_B)) begin
            out_data <= byte_out; out_valid <= 1'b1; out_last <= (state != HEAD || idx >= 3) && (len == 11'd1);
        end else if (fire) out_valid <= 1'b0;
    end

    always @(posedge clk) begin
        if (rst) begin
            state <= IDLE; scanning <= 1'b0;
        end else case (state)
            IDLE: if (start) begin
                r_seq <= seq; r_tx <= tx_mask; r_rx <= rx_mask; r_status <= status;
                r_n <= imu_count; slot <= imu_base; wrd <= 0; hi <= 0;
                len <= {3'd0, len0}; c <= 0; cnt <= 0;
                state <= COUNT;
            end
            COUNT: if (c[8]) begin  // payload length known: header next; first block set up
                state <= HEAD; idx <= 0;
                c <= 0; c0 <= 0; cnt <= 0; ps <= 0; nz <= 0; e <= 0; sh <= 1; left <= 1; part <= 0;
            end else begin
                if (enabled) begin len <= len_next; cnt <= cnt + 1; end
                c <= c + 1;
            end
            HEAD: if (fire) begin
                if (idx >= 3) len <= len_next;
                idx <= idx + 1;
                if (out_last) state <= IDLE;
                else if (idx == 20) state <= (r_n != 0) ? IMU_A : SCAN_A;
            end
            IMU_A: state <= IMU_B;  // address out, word in next clock
            IMU_B: if (fire) begin
                len <= len_next; hi <= !hi;
                if (out_last) state <= IDLE;
                else if (hi) begin
                    if (wrd == 3'd5) begin
                        wrd <= 0; slot <= slot + 1; r_n <= r_n - 1;
                        state <= (r_n == 4'd1) ? SCAN_A : IMU_A;
                    end else begin
                        wrd <= wrd + 1; state <= IMU_A;
                    end
                end
            end
            SCAN_A: if (c[8] || cnt == 4'd8) state <= NORM;
            else if (enabled) begin state <= SCAN_R; scanning <= 1'b1; end
            else c <= c + 1;
            SCAN_R, SCAN_I: begin  // part 0, then 1
                if (gt) begin ps <= sgn; nz <= 1'b1; end
                part <= !part;
                if (state == SCAN_R) state <= SCAN_I;
                else begin cnt <= cnt + 1; c <= c + 1; state <= SCAN_A; scanning <= 1'b0; end
            end
            NORM: if (cond_r) begin
                ps <= ps | R[0]; e <= e + 1;
                if (left) begin left <= 1'b0; sh <= 0; end else sh <= sh + 1;
            end else if (nz && cond_l) begin
                e <= e - 1; sh <= sh + 1;
            end else state <= EXPO;
            EXPO: if (fire) begin
                len <= len_next;
                c <= c0; cnt2 <= 0; ps <= 1'b0; state <= EMIT_A;
            end
            EMIT_A: if (cnt2 == cnt) begin  // block done: the next one starts after its last cell
                c0 <= c; cnt <= 0; ps <= 0; nz <= 0; e <= 0; sh <= 1; left <= 1;
                state <= SCAN_A;
            end else if (enabled) state <= EMIT_L;
            else c <= c + 1;
            EMIT_L: begin
                sc <= nz ? sh : 5'd0; state <= EMIT_S;
            end
            EMIT_S: if (sc != 0) begin
                sc <= sc - 1;
            end else state <= EMIT_B;
            EMIT_B: if (fire) begin
                len <= len_next; hi <= !hi;
                if (out_last) state <= IDLE;
                else if (hi) begin
                    part <= !part;
                    if (!part) state <= EMIT_L;
                    else begin c <= c + 1; cnt2 <= cnt2 + 1; state <= EMIT_A; end
                end
            end
            default: state <= IDLE;
        endcase
    end
endmodule
