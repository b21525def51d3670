// Sinusoidal commutation (thesis 6.2: hall sensors replaced by 15-bit absolute encoders).
// Electrical angle = angle * POLE_PAIRS + offset (mod 2^15). The voltage vector is placed 90
// electrical degrees ahead of the rotor flux (pure torque); phase k gets
//     v_k = amplitude * sin(theta_e + 90 deg - k * 120 deg) / 32768   (k = 0, 1, 2 for a, b, c)
// from one quarter-wave ROM and one multiplier, time-multiplexed over the three phases
// (6 clocks from start to done). amplitude is signed (negative: reverse torque), in PWM counts.
module commutation #(
    parameter POLE_PAIRS = 4  // 57BL / 42BLF: 8 poles
) (
    input wire clk,
    input wire rst,
    input wire start,
    input wire [14:0] angle,  // mechanical, 2^15 per turn
    input wire [14:0] offset,  // electrical zero of this motor (calibration)
    input wire signed [15:0] amplitude,
    output reg signed [15:0] va,
    output reg signed [15:0] vb,
    output reg signed [15:0] vc,
    output reg done
);
    localparam [14:0] DEG90 = 15'd8192;
    localparam [14:0] DEG120 = 15'd10923;  // 2^15 / 3, rounded: 0.004 deg off

    wire [14:0] theta = angle * POLE_PAIRS + offset + DEG90;  // wraps mod 2^15 by width

    reg [14:0] ph;  // stage A: the phase angle being looked up
    reg [1:0] k;  // which phase stage A holds
    reg busy, a_valid, b_valid, c_valid;
    reg [1:0] b_quad, b_k, c_k;
    reg signed [15:0] amp;
    reg signed [31:0] prod;

    wire [9:0] idx = ph[14:5];  // 1024 steps per electrical turn
    wire [7:0] rom_addr = idx[8] ? ~idx[7:0] : idx[7:0];  // quadrants 1 and 3 run backwards
    wire [14:0] rom_q;  // stage B (one clock ROM latency)
    sine_rom rom (.clk(clk), .addr(rom_addr), .q(rom_q));
    wire signed [15:0] s = b_quad[1] ? -$signed({1'b0, rom_q}) : $signed({1'b0, rom_q});

    always @(posedge clk) begin
        if (rst) begin
            busy <= 1'b0;
            a_valid <= 1'b0;
            b_valid <= 1'b0;
            c_valid <= 1'b0;
            done <= 1'b0;
            k <= 0;
            va <= 0;
            vb <= 0;
            vc <= 0;
        end else begin
            done <= 1'b0;
            // stage A: phases a, b, c on three consecutive clocks
            if (start && !busy) begin
                busy <= 1'b1;
                amp <= amplitude;
                ph <= theta;
                k <= 0;
                a_valid <= 1'b1;
            end else if (a_valid && k != 2'd2) begin
                ph <= ph - DEG120;
                k <= k + 1'b1;
            end else begin
                a_valid <= 1'b0;
            end
            // stage B: ROM output, sign from the quadrant
            b_valid <= a_valid;
            b_k <= k;
            b_quad <= idx[9:8];
            // stage C: times the amplitude (one DSP multiplier)
            c_valid <= b_valid;
            c_k <= b_k;
            prod <= amp * s;
            // stage D: scale and store
            if (c_valid) begin
                case (c_k)
                    2'd0: va <= prod >>> 15;
                    2'd1: vb <= prod >>> 15;
                    default: begin
                        vc <= prod >>> 15;
                        done <= 1'b1;
                        busy <= 1'b0;
                    end
                endcase
            end
        end
    end
endmodule
