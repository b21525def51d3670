// UART command parser: host frames (types 10 write, 11 read, 6-byte payload, CRC-32) become bus
// cycles; each well-formed command queues one reply (type 02: type, length and payload; the framer
// adds sync and CRC). Bad frames are dropped and counted (rejected). The parser then waits for its
// reply to be taken by the framer before taking the next byte, which can be a whole frame's time
// when a frame is being sent: host bytes wait in a 32-byte FIFO meanwhile (two further commands; a
// byte that finds it full is lost). Fields are taken on the fly (no frame buffer): the address and
// value shift into bus_addr / bus_wdata, the CRC is compared byte by byte.
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
    // RX FIFO (distributed RAM on the ECP5, sync read): a byte is popped when the parser takes bytes
    // (hunting or in a command body), no popped byte is still on its way (c_valid) and the CRC unit
    // is idle; the parser sees it (c_data, c_valid) the clock after, with its state unchanged.
    reg [7:0] fifo [0:31];  // yosys: 4 TRELLIS_DPR16X4 on the ECP5, one SB_RAM40_4K on the iCE40
    reg [5:0] wp, rp;  // one bit more than the address: full when they differ by 32
    reg [7:0] c_data; reg c_valid;
    wire crc_busy;
    wire put = rx_valid && (wp ^ rp) != 6'b100000;  // not full
    wire pop = (wp != rp) && !c_valid && !crc_busy && (state == HUNT0 || state == HUNT1 || state == BODY);
    always @(posedge clk) begin
        if (put) fifo[wp[4:0]] <= rx_data;
        c_data <= fifo[rp[4:0]];
        c_valid <= pop;
        if (rst) begin wp <= 0; rp <= 0; c_valid <= 1'b0; end
        else begin
            if (put) wp <= wp + 1;
            if (pop) rp <= rp + 1;
        end
    end
    reg [3:0] idx;  // byte after the sync word: type, len(2), address(2), value(4), crc(4)
    wire [31:0] crc;  // over type, length and payload; done before the next byte is popped
    crc32_serial u_crc (.clk(clk), .rst(rst), .init(state == HUNT1), .load(state == BODY && c_valid && idx < 9),
        .data(c_data), .crc(crc), .busy(crc_busy));
    reg is_write, type_ok, len_ok, crc_ok;
    reg [31:0] value;  // reply: the register's value after the command
    reg [1:0] rstat;   // reply status (0 ok, 1 bad address, 2 read-only)
    reg [7:0] crc_rx;  // the CRC byte expected now
    always @* case (idx[1:0])  // idx 9, 10, 11, 12: CRC bytes 0..3
        2'd1: crc_rx = ~crc[7:0];
        2'd2: crc_rx = ~crc[15:8];
        2'd3: crc_rx = ~crc[23:16];
        default: crc_rx = ~crc[31:24];
    endcase
    reg [7:0] rbyte;
    always @* case (idx)
        4'd0: rbyte = 8'h02;
        4'd1: rbyte = 8'd7;
        4'd3: rbyte = bus_addr[7:0];
        4'd4: rbyte = bus_addr[15:8];
        4'd5: rbyte = value[7:0];
        4'd6: rbyte = value[15:8];
        4'd7: rbyte = value[23:16];
        4'd8: rbyte = value[31:24];
        4'd9: rbyte = {6'd0, rstat};
        default: rbyte = 8'd0;
    endcase

    always @(posedge clk) begin
        bus_we <= 1'b0;
        if (rst) begin
            state <= HUNT0; rejected <= 0; out_valid <= 1'b0; out_last <= 1'b0;
        end else case (state)
            HUNT0: if (c_valid && c_data == 8'hA5) state <= HUNT1;
            HUNT1: if (c_valid) begin
                if (c_data == 8'h5A) begin state <= BODY; idx <= 0; end
                else if (c_data != 8'hA5) state <= HUNT0;
            end
            BODY: if (c_valid) begin
                if (idx == 0) begin
                    type_ok <= (c_data[7:1] == 7'h08);  // 0x10 write, 0x11 read
                    is_write <= !c_data[0];
                end
                if (idx == 1) len_ok <= (c_data == 8'd6);
                if (idx == 3 || idx == 4) bus_addr <= {c_data, bus_addr[15:8]};
                if (idx >= 5 && idx <= 8) bus_wdata <= {c_data, bus_wdata[31:8]};
                if (idx == 9) crc_ok <= (c_data == crc_rx);
                else if (idx > 9) crc_ok <= crc_ok && (c_data == crc_rx);
                if (idx == 2 && (!len_ok || c_data != 8'd0)) begin
                    rejected <= rejected + 1; state <= HUNT0;  // wrong length: hunt again
                end else if (idx == 12) state <= EXEC;
                idx <= idx + 1;
            end
            EXEC: begin
                if (type_ok && crc_ok) begin
                    bus_we <= is_write;
                    state <= REPLY; idx <= 0;
                end else begin
                    rejected <= rejected + 1; state <= HUNT0;
                end
            end
            REPLY: begin
                // Status during the bus cycle (a write to a read-only register), value after it.
                if (idx == 0 && !out_valid) rstat <= bus_status[1:0];
                if (idx == 1 && !out_valid) value <= bus_rdata;
                if (!out_valid) begin
                    out_valid <= 1'b1; out_data <= rbyte; out_last <= (idx == 9);
                end else if (out_ready) begin
                    out_valid <= 1'b0;
                    if (idx == 9) state <= HUNT0;
                    idx <= idx + 1;
                end
            end
            default: state <= HUNT0;
        endcase
    end
endmodule
