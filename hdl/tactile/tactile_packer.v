// Frame packer: header, shared-exponent blocks of the enabled cells, CRC-32, as
// shared/protocols/tactile.py encode_frame (byte-exact; checked against the vectors file).
// Reads the frame memory at rd_addr = {excitation line, reception line} (64 bits {im, re},
// registered read, one cycle latency). No IMU samples (count 0).
module tactile_packer (
    input  wire clk, input wire rst, input wire start,
    input  wire [31:0] seq, input wire [63:0] ts,
    input  wire [15:0] tx_mask, input wire [15:0] rx_mask, input wire [7:0] status,
    output wire [7:0] rd_addr, input wire [63:0] rd_data,
    output reg  [7:0] out_data, output reg out_valid, output reg out_last, input wire out_ready,
    output wire busy
);
    localparam IDLE = 0, HEAD = 1, SCAN_A = 2, SCAN_D = 3, EXPB = 4, EMIT_A = 5, EMIT_D = 6, EMIT_B = 7,
               CRC = 8;
    reg [3:0] state;
    reg [31:0] r_seq; reg [63:0] r_ts; reg [15:0] r_tx, r_rx; reg [7:0] r_status;
    reg [8:0] c, c0, c_end;   // cell index {k, j}, 256 = past the end
    reg [3:0] cnt, cnt2;  // cells in this block (<= 8), cells emitted
    reg [8:0] cells_done;
    reg [31:0] peak;
    reg signed [7:0] e;
    reg [15:0] m_re, m_im;
    reg [4:0] idx;
    reg [31:0] crc;
    wire [31:0] crc_next;
    crc32_byte u_crc (.crc_in(crc), .data(out_data), .crc_out(crc_next));
    assign busy = (state != IDLE);
    assign rd_addr = c[7:0];

    function [4:0] popcount16;
        input [15:0] x;
        integer i;
        begin
            popcount16 = 0;
            for (i = 0; i < 16; i = i + 1) popcount16 = popcount16 + x[i];
        end
    endfunction
    wire [8:0] ncells = popcount16(r_tx) * popcount16(r_rx);
    wire [9:0] nvals = {ncells, 1'b0};
    wire [15:0] length = 16'd18 + ((nvals + 10'd15) >> 4) + {nvals, 1'b0};
    wire enabled = !c[8] && r_tx[c[7:4]] && r_rx[c[3:0]];
    wire [31:0] re = rd_data[31:0];
    wire [31:0] im = rd_data[63:32];
    wire [31:0] abs_re = re[31] ? -re : re;
    wire [31:0] abs_im = im[31] ? -im : im;

    // Smallest e with peak <= 32767 * 2^e (-128 for a zero block).
    function signed [7:0] expo;
        input [31:0] p;
        integer k;
        begin
            expo = -8'sd128;
            if (p != 0)
                for (k = 17; k >= -14; k = k - 1)
                    if (k >= 0 ? ({16'd0, p} <= (48'd32767 << k)) : (({16'd0, p} << (-k)) <= 48'd32767))
                        expo = k;
        end
    endfunction
    // Round half up: (v + 2^(e-1)) >>> e, or v << -e.
    function [15:0] mant;
        input [31:0] v;
        input signed [7:0] ex;
        reg signed [47:0] x;
        begin
            x = {{16{v[31]}}, v};
            if (ex > 0) x = (x + (48'sd1 <<< (ex - 1))) >>> ex;
            else x = x <<< (-ex);
            mant = x[15:0];
        end
    endfunction

    reg [7:0] head_byte;
    always @* begin
        case (idx)
            0: head_byte = 8'hA5; 1: head_byte = 8'h5A; 2: head_byte = 8'h01;
            3: head_byte = length[7:0]; 4: head_byte = length[15:8];
            5, 6, 7, 8: head_byte = r_seq[8 * (idx - 5) +: 8];
            9, 10, 11, 12, 13, 14, 15, 16: head_byte = r_ts[8 * (idx - 9) +: 8];
            17: head_byte = r_tx[7:0]; 18: head_byte = r_tx[15:8];
            19: head_byte = r_rx[7:0]; 20: head_byte = r_rx[15:8];
            21: head_byte = r_status;
            default: head_byte = 8'd0;  // 22: IMU sample count
        endcase
    end

    always @(posedge clk) begin
        if (rst) begin
            state <= IDLE; out_valid <= 1'b0; out_last <= 1'b0;
        end else case (state)
            IDLE: if (start) begin
                r_seq <= seq; r_ts <= ts; r_tx <= tx_mask; r_rx <= rx_mask; r_status <= status;
                state <= HEAD; idx <= 0; crc <= 32'hFFFFFFFF;
                c <= 0; c0 <= 0; cnt <= 0; peak <= 0; cells_done <= 0;
            end
            HEAD: if (!out_valid) begin
                out_data <= head_byte; out_valid <= 1'b1;
            end else if (out_ready) begin
                out_valid <= 1'b0;
                if (idx >= 2) crc <= crc_next;
                idx <= (idx == 22) ? 5'd0 : idx + 1;
                if (idx == 22) state <= (ncells == 0) ? CRC : SCAN_A;
            end
            SCAN_A: if (c[8] || cnt == 8) begin
                c_end <= c; state <= EXPB;
            end else if (enabled) state <= SCAN_D;
            else c <= c + 1;
            SCAN_D: begin
                if (abs_re > peak && abs_re >= abs_im) peak <= abs_re;
                else if (abs_im > peak) peak <= abs_im;
                cnt <= cnt + 1; c <= c + 1; state <= SCAN_A;
            end
            EXPB: if (!out_valid) begin
                e <= expo(peak); out_data <= expo(peak); out_valid <= 1'b1;
            end else if (out_ready) begin
                out_valid <= 1'b0; crc <= crc_next;
                c <= c0;  // second pass over the block: mantissas
                state <= EMIT_A; cnt2 <= 0;
            end
            EMIT_A: if (cnt2 == cnt) begin
                cells_done <= cells_done + cnt;
                if (cells_done + cnt == ncells) begin state <= CRC; idx <= 0; end
                else begin c <= c_end; c0 <= c_end; cnt <= 0; peak <= 0; state <= SCAN_A; end
            end else if (enabled) state <= EMIT_D;
            else c <= c + 1;
            EMIT_D: begin
                m_re <= mant(re, e); m_im <= mant(im, e); idx <= 0; state <= EMIT_B;
            end
            EMIT_B: if (!out_valid) begin
                case (idx[1:0])
                    0: out_data <= m_re[7:0]; 1: out_data <= m_re[15:8];
                    2: out_data <= m_im[7:0]; default: out_data <= m_im[15:8];
                endcase
                out_valid <= 1'b1;
            end else if (out_ready) begin
                out_valid <= 1'b0; crc <= crc_next; idx <= idx + 1;
                if (idx == 3) begin c <= c + 1; cnt2 <= cnt2 + 1; state <= EMIT_A; end
            end
            CRC: if (!out_valid) begin
                out_data <= ~crc[8 * idx[1:0] +: 8]; out_valid <= 1'b1; out_last <= (idx == 3);
            end else if (out_ready) begin
                out_valid <= 1'b0; out_last <= 1'b0; idx <= idx + 1;
                if (idx == 3) state <= IDLE;
            end
            default: state <= IDLE;
        endcase
    end
endmodule
