// UART command parser: host frames (types 10 write, 11 read, 6-byte payload, CRC-32) become bus
// cycles; each well-formed command queues one reply frame (type 02). Bad frames are dropped and
// counted (rejected). The parser then waits for its reply to be sent before taking the next one.
module tactile_cmd (
    input  wire clk, input wire rst,
    input  wire [7:0] rx_data, input wire rx_valid,
    output reg  [15:0] bus_addr, output reg [31:0] bus_wdata, output reg bus_we,
    input  wire [31:0] bus_rdata, input wire [7:0] bus_status,
    output reg  [7:0] out_data, output reg out_valid, output reg out_last, input wire out_ready,
    output reg  [15:0] rejected
);
    localparam HUNT0 = 0, HUNT1 = 1, BODY = 2, EXEC = 3, REPLY = 4;
    reg [2:0] state;
    reg [3:0] idx;
    reg [7:0] buf_ [0:14];  // type, len(2), payload(6), crc(4)
    reg [31:0] crc;
    wire [31:0] crc_next;
    reg [7:0] crc_byte;
    crc32_byte u_crc (.crc_in(crc), .data(crc_byte), .crc_out(crc_next));
    reg [55:0] reply;  // address(2), value(4), status(1)
    reg [4:0] ridx;
    reg [7:0] rbyte;
    wire [31:0] rx_crc = {buf_[12], buf_[11], buf_[10], buf_[9]};
    wire good = (buf_[0] == 8'h10 || buf_[0] == 8'h11) && buf_[1] == 8'd6 && buf_[2] == 8'd0 && rx_crc == ~crc;

    always @* begin
        case (ridx)
            0: rbyte = 8'hA5; 1: rbyte = 8'h5A; 2: rbyte = 8'h02; 3: rbyte = 8'd7; 4: rbyte = 8'd0;
            12: rbyte = ~crc[7:0]; 13: rbyte = ~crc[15:8]; 14: rbyte = ~crc[23:16]; 15: rbyte = ~crc[31:24];
            default: rbyte = reply[8 * (ridx - 5) +: 8];
        endcase
        crc_byte = (state == REPLY) ? rbyte : rx_data;
    end

    always @(posedge clk) begin
        bus_we <= 1'b0;
        if (rst) begin
            state <= HUNT0; rejected <= 0; out_valid <= 1'b0; out_last <= 1'b0;
        end else case (state)
            HUNT0: if (rx_valid && rx_data == 8'hA5) state <= HUNT1;
            HUNT1: if (rx_valid) begin
                if (rx_data == 8'h5A) begin state <= BODY; idx <= 0; crc <= 32'hFFFFFFFF; end
                else if (rx_data != 8'hA5) state <= HUNT0;
            end
            BODY: if (rx_valid) begin
                buf_[idx] <= rx_data;
                if (idx < 9) crc <= crc_next;
                if (idx == 2 && (buf_[1] != 8'd6 || rx_data != 8'd0)) begin
                    rejected <= rejected + 1; state <= HUNT0;  // wrong length: hunt again
                end else if (idx == 12) state <= EXEC;
                idx <= idx + 1;
            end
            EXEC: begin
                if (good) begin
                    bus_addr <= {buf_[4], buf_[3]};
                    bus_wdata <= {buf_[8], buf_[7], buf_[6], buf_[5]};
                    bus_we <= (buf_[0] == 8'h10);
                    state <= REPLY; ridx <= 0; crc <= 32'hFFFFFFFF;
                end else begin
                    rejected <= rejected + 1; state <= HUNT0;
                end
            end
            REPLY: begin
                // Status during the bus cycle (a write to a read-only register), value after it.
                if (ridx == 0 && !out_valid) reply[55:48] <= bus_status;
                if (ridx == 1 && !out_valid) reply[47:0] <= {bus_rdata, bus_addr};
                if (!out_valid) begin
                    out_valid <= 1'b1; out_data <= (ridx == 0) ? 8'hA5 : rbyte; out_last <= (ridx == 15);
                end else if (out_ready) begin
                    if (ridx >= 2 && ridx < 12) crc <= crc_next;
                    out_valid <= 1'b0;
                    if (ridx == 15) state <= HUNT0;
                    ridx <= ridx + 1;
                end
            end
            default: state <= HUNT0;
        endcase
    end
endmodule
