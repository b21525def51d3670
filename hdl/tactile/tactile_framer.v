// Device -> host framing (shared/protocols/framing.py) for both sources of the core: sync A5 5A,
// then the source's bytes (type, length, payload; `last` on the final one), then the CRC-32 over
// them. Source a (register replies) has priority over source b (frames) when both wait; a frame is
// never interleaved with a reply. One CRC unit for everything the core sends.
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
    reg [31:0] crc;
    wire [7:0] src_data = sel ? b_data : a_data;
    wire src_valid = sel ? b_valid : a_valid;
    wire src_last = sel ? b_last : a_last;
    wire [31:0] crc_next;
    crc32_byte u_crc (.crc_in(crc), .data(src_data), .crc_out(crc_next));
    reg [7:0] crc_byte;
    always @* case (idx)
        2'd0: crc_byte = ~crc[7:0];
        2'd1: crc_byte = ~crc[15:8];
        2'd2: crc_byte = ~crc[23:16];
        default: crc_byte = ~crc[31:24];
    endcase
    assign tx_data = (state == SYNC0) ? 8'hA5 : (state == SYNC1) ? 8'h5A : (state == CRC) ? crc_byte : src_data;
    assign tx_valid = (state == SYNC0) || (state == SYNC1) || (state == CRC) || (state == BODY && src_valid);
    assign a_ready = (state == BODY) && !sel && tx_ready;
    assign b_ready = (state == BODY) && sel && tx_ready;
    assign busy = (state != IDLE);
    assign tx_last = (state == CRC) && (idx == 2'd3);
    // CRC register: set over enable (maps onto the flip-flops' own set input)
    always @(posedge clk)
        if (state == SYNC1) crc <= 32'hFFFFFFFF;
        else if (state == BODY && src_valid && tx_ready) crc <= crc_next;
    always @(posedge clk) begin
        if (rst) state <= IDLE;
        else case (state)
            IDLE: if (a_valid || b_valid) begin sel <= !a_valid; state <= SYNC0; end
            SYNC0: if (tx_ready) state <= SYNC1;
            SYNC1: if (tx_ready) state <= BODY;
            BODY: if (src_valid && tx_ready && src_last) begin state <= CRC; idx <= 0; end
            CRC: if (tx_ready) begin
                idx <= idx + 1;
                if (idx == 2'd3) state <= IDLE;
            end
            default: state <= IDLE;
        endcase
    end
endmodule
