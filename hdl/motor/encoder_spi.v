// SPI master for an A1333-style absolute angle sensor (simplified frame): SPI mode 3 (SCLK idles
// high, both sides change data on the falling edge and sample on the rising edge), 16-bit frames,
// MSB first. Every frame sends READ_CMD and receives the answer to the previous frame's command;
// reading the same angle register continuously, each answer is the angle:
// bit 15 = error flag (sensor diagnostics), bits 14:0 = angle, 2^15 per turn.
module encoder_spi #(
    parameter HALF = 3,  // clocks per SCLK half period: 50 MHz / 6 = 8.3 MHz (A1333: <= 10 MHz)
    parameter CS_GAP = 10,  // clocks CS stays high between frames (and CS-to-SCLK setup)
    parameter [15:0] READ_CMD = 16'h2000  // read of the angle register
) (
    input wire clk,
    input wire rst,
    input wire start,  // begin a frame (ignored while busy)
    output reg cs_n,
    output reg sclk,
    output reg mosi,
    input wire miso,
    output reg [14:0] angle,
    output reg error,  // the sensor's error flag, or MISO stuck (all ones)
    output reg valid,  // one clock when angle/error are new
    output wire busy
);
    localparam S_IDLE = 2'd0, S_SETUP = 2'd1, S_SHIFT = 2'd2, S_GAP = 2'd3;
    reg [1:0] state;
    reg [7:0] timer;
    reg [4:0] nbit;
    reg [15:0] tx, rx;
    assign busy = state != S_IDLE;

    always @(posedge clk) begin
        if (rst) begin
            state <= S_IDLE;
            cs_n <= 1'b1;
            sclk <= 1'b1;
            mosi <= 1'b1;
            valid <= 1'b0;
            error <= 1'b0;
            angle <= 0;
            timer <= 0;
        end else begin
            valid <= 1'b0;
            case (state)
                S_IDLE: if (start) begin
                    cs_n <= 1'b0;
                    tx <= READ_CMD;
                    nbit <= 0;
                    timer <= 0;
                    state <= S_SETUP;
                end
                S_SETUP: if (timer == HALF - 1) begin  // CS-to-first-edge setup
                    timer <= 0;
                    sclk <= 1'b0;  // falling edge: present bit 15
                    mosi <= tx[15];
                    tx <= {tx[14:0], 1'b0};
                    state <= S_SHIFT;
                end else timer <= timer + 1'b1;
                S_SHIFT: if (timer == HALF - 1) begin
                    timer <= 0;
                    if (!sclk) begin  // rising edge: sample
                        sclk <= 1'b1;
                        rx <= {rx[14:0], miso};
                        nbit <= nbit + 1'b1;
                    end else if (nbit == 16) begin  // last rising edge done: end of frame
                        cs_n <= 1'b1;
                        mosi <= 1'b1;
                        angle <= rx[14:0];
                        error <= rx[15] | (&rx);
                        valid <= 1'b1;
                        state <= S_GAP;
                    end else begin  // falling edge: next bit
                        sclk <= 1'b0;
                        mosi <= tx[15];
                        tx <= {tx[14:0], 1'b0};
                    end
                end else timer <= timer + 1'b1;
                default: if (timer == CS_GAP - 1) begin  // S_GAP
                    timer <= 0;
                    state <= S_IDLE;
                end else timer <= timer + 1'b1;
            endcase
        end
    end
endmodule
