// 8N1 UART, DIV system clocks per bit. Byte interfaces use valid/ready.
module uart_tx #(parameter DIV = 4) (
    input  wire clk, input wire rst,
    input  wire [7:0] data, input wire valid, output wire ready,
    output reg  tx
);
    localparam CW = (DIV > 2) ? $clog2(DIV) : 1;
    reg [9:0] shift;
    reg [3:0] nbits;
    reg [CW-1:0] cnt;
    assign ready = (nbits == 0);
    always @(posedge clk) begin
        if (rst) begin
            tx <= 1'b1; nbits <= 0; cnt <= 0; shift <= 10'h3FF;
        end else if (nbits == 0) begin
            if (valid) begin
                shift <= {1'b1, data, 1'b0};
                nbits <= 10; cnt <= 0;
            end
        end else begin
            tx <= shift[0];
            if (cnt == DIV - 1) begin
                cnt <= 0; shift <= {1'b1, shift[9:1]}; nbits <= nbits - 1;
            end else cnt <= cnt + 1;
        end
    end
endmodule

module uart_rx #(parameter DIV = 4) (
    input  wire clk, input wire rst, input wire rx,
    output reg [7:0] data, output reg valid
);
    localparam CW = (DIV > 2) ? $clog2(DIV) : 1;
    reg [1:0] sync;
    reg [3:0] nbits;
    reg [CW-1:0] cnt;
    reg [8:0] shift;
    always @(posedge clk) begin
        sync <= {sync[0], rx};
        valid <= 1'b0;
        if (rst) begin
            nbits <= 0; cnt <= 0; sync <= 2'b11;
        end else if (nbits == 0) begin
            if (!sync[1]) begin  // start bit: sample mid-bit from here on
                nbits <= 10; cnt <= DIV / 2;
            end
        end else if (cnt == DIV - 1) begin
            cnt <= 0; nbits <= nbits - 1;
            shift <= {sync[1], shift[8:1]};
            if (nbits == 1) begin
                data <= shift[8:1];
                valid <= sync[1];  // stop bit must be high
            end
        end else cnt <= cnt + 1;
    end
endmodule
