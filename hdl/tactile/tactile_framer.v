// Device -> host framing (shared/protocols/framing.py) for both sources of the core: sync A5 5A,
// then the source's bytes (type, length, payload; `last` on the final one), then the CRC-32 over
// them. Source a (register replies) has priority over source b (frames) when both wait; a frame is
// never interleaved with a reply. One (bit-serial) CRC unit for everything the core sends.
module tactile_framer (
    input  wire clk, input wire rst,
    input  wire [7:0] a_data, input wire a_valid, input wire a_last, output wire a_ready,
    input  wire [7:0] b_data, input wire b_valid, input wire b_last, output wire b_ready,
    output wire [7:0] tx_data, output wire tx_valid, input wire tx_ready,
    output wire busy, output wire tx_last
);
    localparam IDLE = 0, SYNC0 = 1, SYNC1 = 2, BODY = 3, CRC = 4;
    reg [2:0] state;
    reg sel;  // 0: a, 1: b
    reg [1:0] idx;
    wire [31:0] crc; wire crc_busy;
    wire [7:0] src_data = sel ? b_data : a_data;
    wire src_valid = sel ? b_valid : a_valid;
    wire src_last = sel ? b_last : a_last;
    crc32_serial u_crc (.clk(clk), .rst(rst), .init(state == SYNC1), .load(state == BODY && src_valid && go),
        .data(src_data), .crc(crc), .busy(crc_busy));
    reg [7:0] crc_byte;
    always @* case (idx)
        2'd0: crc_byte = ~crc[7:0];
        2'd1: crc_byte = ~crc[15:8];
        2'd2: crc_byte = ~crc[23:16];
        default: crc_byte = ~crc[31:24];
    endcase
    assign tx_data = (state == SYNC0) ? 8'hA5 : (state == SYNC1) ? 8'h5A : (state == CRC) ? crc_byte : src_data;
    // crc_busy is never high when the UART takes a byte (10 clocks a byte); it only guards it here
    wire go = tx_ready && !crc_busy;
    assign tx_valid = !crc_busy && ((state == SYNC0) || (state == SYNC1) || (state == CRC) ||
                                    (state == BODY && src_valid));
    assign a_ready = (state == BODY) && !sel && go;
    assign b_ready = (state == BODY) && sel && go;
    assign busy = (state != IDLE);
    assign tx_last = (state == CRC) && (idx == 2'd3);
    always @(posedge clk) begin
        if (rst) state <= IDLE;
        else case (state)
            IDLE: if (a_valid || b_valid) begin sel <= !a_valid; state <= SYNC0; end
            SYNC0: if (go) state <= SYNC1;
            SYNC1: if (go) state <= BODY;
            BODY: if (src_valid && go && src_last) begin state <= CRC; idx <= 0; end
            CRC: if (go) begin
                idx <= idx + 1;
                if (idx == 2'd3) state <= IDLE;
            end
            default: state <= IDLE;
        endcase
    end
endmodule
