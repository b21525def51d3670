// CRC-32 (IEEE 802.3, reflected, poly 0xEDB88320), as zlib.crc32, one bit per clock: `init` sets
// the register to all ones; `load` takes a byte, which is then shifted in LSB first over the next 8
// clocks (busy). The bytes of a UART come at least 10 clocks apart, so a byte is done before the
// next one. The register holds the complemented CRC: send ~crc LSB first.
module crc32_serial (
    input  wire clk, input wire rst,
    input  wire init, input wire load, input wire [7:0] data,
    output reg  [31:0] crc, output wire busy
);
    reg [7:0] d;
    reg [3:0] n;  // bits left
    assign busy = (n != 0);
    wire fb = crc[0] ^ d[0];
    always @(posedge clk) begin
        if (rst) n <= 4'd0;
        else if (load) begin d <= data; n <= 4'd8; end
        else if (busy) begin d <= d >> 1; n <= n - 1; end
        if (init) crc <= 32'hFFFFFFFF;  // set over enable: the flip-flops' own set input
        else if (busy) crc <= (crc >> 1) ^ (fb ? 32'hEDB88320 : 32'd0);
    end
endmodule
